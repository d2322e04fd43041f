"""Array-level 2D geometry: least-squares similarity transforms, affine maps and thin-plate splines.

Upstream of every stage (numpy only, no torch): the data layer's synthetic subject, the
face model's Procrustes analysis and the ERI feature points all use these.

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
training and application", CVIU 61(1), 1995 (generalised Procrustes alignment).
S. Umeyama, "Least-squares estimation of transformation parameters between two point
patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import numpy as np


def similarity_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity transforms mapping ``src`` onto ``dst`` (Umeyama, no reflection).

    Parameters
    ----------
    src, dst : np.ndarray
        (..., K, 2) point sets; leading axes broadcast.

    Returns
    -------
    np.ndarray
        (..., 2, 3) float64 matrices ``M`` with ``dst ~= src @ M[:, :2].T + M[:, 2]``.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    mu_s = src.mean(-2, keepdims=True)
    mu_d = dst.mean(-2, keepdims=True)
    s = src - mu_s
    d = dst - mu_d
    # For 2D similarity the optimum has closed form: rotation angle from the cross terms.
    a = (s * d).sum((-1, -2))  # sum x_s x_d + y_s y_d
    b = (s[..., 0] * d[..., 1] - s[..., 1] * d[..., 0]).sum(-1)
    var_s = (s**2).sum((-1, -2))
    norm = np.hypot(a, b)
    scale = np.where(var_s > 0, norm / np.where(var_s > 0, var_s, 1), 1.0)
    cos = np.where(norm > 0, a / np.where(norm > 0, norm, 1), 1.0)
    sin = np.where(norm > 0, b / np.where(norm > 0, norm, 1), 0.0)
    r = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2) * scale[..., None, None]
    t = mu_d[..., 0, :] - (mu_s[..., 0, :, None] * r.swapaxes(-1, -2)[..., :, :]).sum(-2)
    return np.concatenate([r, t[..., :, None]], -1)


def apply_affine(points: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Apply (..., 2, 3) affine matrices to (..., K, 2) points."""
    m = np.asarray(m)
    return np.einsum("...ij,...kj->...ki", m[..., :2], points) + m[..., None, :, 2]


def invert_affine(m: np.ndarray) -> np.ndarray:
    """Inverse of (..., 2, 3) affine matrices."""
    a = np.linalg.inv(np.asarray(m, np.float64)[..., :2])
    t = -np.einsum("...ij,...j->...i", a, m[..., 2])
    return np.concatenate([a, t[..., None]], -1)


def normalise_shape(shape: np.ndarray) -> np.ndarray:
    """Centre (K, 2) points on the origin and scale them to unit Frobenius norm."""
    c = shape - shape.mean(0)
    return c / np.linalg.norm(c)


def generalised_procrustes(
    shapes: np.ndarray, max_iter: int = 100, tol: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised Procrustes alignment under similarity transforms (Cootes et al., CVIU 1995).

    Parameters
    ----------
    shapes : np.ndarray
        (N, K, 2) point sets.
    max_iter, tol : int, float
        Iterate until the mean moves by less than ``tol`` (Frobenius norm).

    Returns
    -------
    aligned : np.ndarray
        (N, K, 2) float64 shapes similarity-aligned to the mean.
    mean : np.ndarray
        (K, 2) float64 mean shape, centred, unit norm, rotated like the first shape.
    """
    shapes = np.asarray(shapes, np.float64)
    ref = normalise_shape(shapes[0])
    mean = ref
    for _ in range(max_iter):
        aligned = apply_affine(shapes, similarity_fit(shapes, mean[None]))
        new = normalise_shape(aligned.mean(0))
        new = apply_affine(new, similarity_fit(new, ref))  # fix the gauge: rotation of the first shape
        new = normalise_shape(new)
        delta = np.linalg.norm(new - mean)
        mean = new
        if delta < tol:
            break
    aligned = apply_affine(shapes, similarity_fit(shapes, mean[None]))
    return aligned, mean


TPS_SMOOTH = 1e-6  # relative regularisation of the spline (coincident control points)


def thin_plate(ctrl: np.ndarray, values: np.ndarray, at: np.ndarray, smooth: float = TPS_SMOOTH) -> np.ndarray:
    """Thin-plate spline through ``values`` (K, 2) at ``ctrl`` (K, 2), evaluated at ``at``
    (N, 2) -> (N, 2) (kernel r^2 log r, affine part; ``smooth`` x the mean kernel on the
    diagonal keeps coincident control points solvable)."""
    c = np.asarray(ctrl, np.float64)
    k = len(c)
    scale = float(np.ptp(c, 0).max()) or 1.0
    cn, an = c / scale, np.asarray(at, np.float64) / scale

    def kernel(r2):
        return 0.5 * r2 * np.log(np.where(r2 > 0, r2, 1.0))

    kk = kernel(((cn[:, None] - cn[None]) ** 2).sum(-1))
    kk += np.eye(k) * smooth * (np.abs(kk).mean() or 1.0)
    p = np.concatenate([np.ones((k, 1)), cn], 1)
    a = np.zeros((k + 3, k + 3))
    a[:k, :k], a[:k, k:], a[k:, :k] = kk, p, p.T
    rhs = np.zeros((k + 3, 2))
    rhs[:k] = values
    coef = np.linalg.solve(a, rhs)
    ka = kernel(((an[:, None] - cn[None]) ** 2).sum(-1))
    return ka @ coef[:k] + np.concatenate([np.ones((len(an), 1)), an], 1) @ coef[k:]


def mirror(x, hi):
    """``x`` reflected into [0, hi] about 0 and ``hi`` (one reflection each way: exact for x in
    [-hi, 2 hi]; the ``BORDER_REFLECT_101`` of a pixel coordinate, hi the last pixel). numpy
    arrays or torch tensors alike (the full-frame warp and its graph share it)."""
    return hi - abs(hi - abs(x))
