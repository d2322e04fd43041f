"""Head pose from 2D-3D correspondences: DLT, normalised DLT, K/R/C decomposition, and
one entry point :func:`solve_pose` over the project's solvers and OpenCV's ``solvePnP``.

Conventions (image y down, camera z forward, ``X_c = R X_m + t``) are those of
:mod:`facesynth.mesh.camera`.

References
----------
Hartley & Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed., sections 7.1
(DLT), 4.4.4 (normalisation) and 6.2.4 (decomposition of P into K [R | -R C]).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from facesynth.errors import FacesynthError
from facesynth.mesh.camera import project, projection_matrix
from facesynth.mesh.epnp import epnp

METHODS = ("dlt", "ndlt", "epnp", "cv-epnp", "cv-sqpnp", "cv-iterative")


def _check_correspondences(X: np.ndarray, x: np.ndarray, minimum: int) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, float)
    x = np.asarray(x, float)
    if X.ndim != 2 or X.shape[1] != 3 or x.shape != (len(X), 2):
        raise FacesynthError(f"pose: expected 3D points (N, 3) and 2D points (N, 2), got {X.shape} and {x.shape}")
    if len(X) < minimum:
        raise FacesynthError(f"pose: need at least {minimum} correspondences, got {len(X)}")
    if not (np.isfinite(X).all() and np.isfinite(x).all()):
        raise FacesynthError("pose: correspondences contain NaN/inf")
    return X, x


def dlt(X: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Direct linear transform: the camera matrix P (3, 4) with ``x ~ P [X; 1]``.

    Parameters
    ----------
    X : (N, 3) world (mesh) points, N >= 6, not all coplanar.
    x : (N, 2) pixels.

    Returns
    -------
    P : (3, 4), scaled to unit Frobenius norm with a positive depth for the first point.

    Each correspondence gives two rows of A p = 0 (H&Z eq. 7.2); p is the right singular
    vector of A with the smallest singular value.
    """
    X, x = _check_correspondences(X, x, 6)
    n = len(X)
    Xh = np.column_stack([X, np.ones(n)])
    A = np.zeros((2 * n, 12))
    A[0::2, 4:8] = -Xh
    A[0::2, 8:12] = x[:, 1:2] * Xh
    A[1::2, 0:4] = Xh
    A[1::2, 8:12] = -x[:, 0:1] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4)
    return _fix_sign(P, X)


def _fix_sign(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Scale P to unit norm and choose the sign that puts the points in front (depth > 0)."""
    P = P / np.linalg.norm(P)
    depth = np.sign(np.linalg.det(P[:, :3])) * (X @ P[2, :3] + P[2, 3])
    return -P if np.median(depth) < 0 else P


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Similarity T ((d+1), (d+1)): centroid to origin, mean distance sqrt(d) (H&Z 4.4.4)."""
    d = pts.shape[1]
    c = pts.mean(axis=0)
    s = np.sqrt(d) / max(np.linalg.norm(pts - c, axis=1).mean(), 1e-300)
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def normalised_dlt(X: np.ndarray, x: np.ndarray) -> np.ndarray:
    """DLT on Hartley-normalised coordinates, de-normalised: ``P = T^-1 P_n U``.

    Same inputs and output as :func:`dlt`. The 2D points are moved to zero mean and
    mean distance sqrt(2), the 3D points to zero mean and mean distance sqrt(3), which
    makes A well conditioned (H&Z algorithm 7.1).
    """
    X, x = _check_correspondences(X, x, 6)
    T = _normaliser(x)
    U = _normaliser(X)
    xn = x @ T[:2, :2].T + T[:2, 2]
    Xn = X @ U[:3, :3].T + U[:3, 3]
    Pn = dlt(Xn, xn)
    return _fix_sign(np.linalg.inv(T) @ Pn @ U, X)


def decompose_krc(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split a finite camera P (3, 4) into ``K (3, 3), R (3, 3), C (3,)``: ``P ~ K R [I | -C]``.

    K is upper triangular with positive diagonal and ``K[2, 2] = 1``; R is a rotation
    (det +1); C is the camera centre (``P [C; 1] = 0``). RQ decomposition by
    ``scipy.linalg.rq`` (H&Z 6.2.4). The overall sign of P is chosen so that det R = +1.
    """
    P = np.asarray(P, float)
    if P.shape != (3, 4):
        raise FacesynthError(f"decompose_krc: P must be (3, 4), got {P.shape}")
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-300:
        raise FacesynthError("decompose_krc: P[:, :3] is singular (camera at infinity)")
    if np.linalg.det(M) < 0:
        P, M = -P, -M
    K, R = scipy.linalg.rq(M)
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R
    C = -np.linalg.solve(M, P[:, 3])
    return K / K[2, 2], R, C


def compose_krc(K: np.ndarray, R: np.ndarray, C: np.ndarray) -> np.ndarray:
    """P = K R [I | -C], shape (3, 4): the inverse of :func:`decompose_krc`."""
    return projection_matrix(K, R, -np.asarray(R) @ np.asarray(C))


@dataclass
class Pose:
    """One camera pose: ``X_c = R X_m + t`` and intrinsics K (estimated by DLT, given otherwise)."""

    R: np.ndarray
    t: np.ndarray
    K: np.ndarray

    @property
    def P(self) -> np.ndarray:
        return projection_matrix(self.K, self.R, self.t)

    def reprojection_error(self, X: np.ndarray, x: np.ndarray) -> float:
        """Mean pixel distance between ``project(P, X)`` and x."""
        return float(np.linalg.norm(project(self.P, X) - x, axis=1).mean())


def _pose_from_p(P: np.ndarray) -> Pose:
    K, R, C = decompose_krc(P)
    return Pose(R, -R @ C, K)


def solve_pose(X: np.ndarray, x: np.ndarray, K: np.ndarray | None = None, method: str = "epnp") -> Pose:
    """Camera pose from correspondences with any of :data:`METHODS`.

    Parameters
    ----------
    X : (N, 3) mesh points; x : (N, 2) pixels.
    K : (3, 3) intrinsics. Required by the PnP methods; the DLT methods estimate their
        own K (returned in the Pose) and ignore it.
    method : ``dlt``, ``ndlt`` (the project's DLT / normalised DLT + KRC decomposition),
        ``epnp`` (the project's EPnP), ``cv-epnp``, ``cv-sqpnp``, ``cv-iterative``
        (OpenCV ``solvePnP`` with SOLVEPNP_EPNP / SQPNP / ITERATIVE).
    """
    if method in ("dlt", "ndlt"):
        return _pose_from_p((dlt if method == "dlt" else normalised_dlt)(X, x))
    if method not in METHODS:
        raise FacesynthError(f"pose: unknown method '{method}' (choose from {', '.join(METHODS)})")
    if K is None:
        raise FacesynthError(f"pose: method '{method}' needs intrinsics K")
    X, x = _check_correspondences(X, x, 4 if method != "cv-iterative" else 6)
    K = np.asarray(K, float)
    if method == "epnp":
        R, t = epnp(X, x, K)
        return Pose(R, t, K)
    import cv2

    flag = {"cv-epnp": cv2.SOLVEPNP_EPNP, "cv-sqpnp": cv2.SOLVEPNP_SQPNP, "cv-iterative": cv2.SOLVEPNP_ITERATIVE}[method]
    ok, rvec, tvec = cv2.solvePnP(X.astype(np.float64), x.astype(np.float64), K, None, flags=flag)
    if not ok:
        raise FacesynthError(f"pose: OpenCV solvePnP ({method}) failed")
    return Pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3), K)
