"""Head-movement and expression transfer from 2D landmarks to a 3D face mesh.

Per frame i with landmarks Q_i (68, 2):

1. **Pose** (R_i, t_i) of the neutral mesh from the rigid landmarks (:data:`POSE_LANDMARKS`:
   face outline at the ears, nose, eye corners) by :func:`facesynth.mesh.pose.solve_pose`,
   optionally smoothed over time (:mod:`facesynth.mesh.smoothing`).
2. **Movement vectors** E_i (68, 2), pixels:

   - *transformation method*: a 2D similarity (Umeyama 1991) aligns the neutral reference
     frame's landmarks Q_0 to Q_i on the rigid inner points (:data:`ALIGN_LANDMARKS`);
     ``E_i = Q_i - align(Q_0)``, scaled by the mouth-width ratio
     ``|p_48 - p_54| / |align(Q_0)_48 - align(Q_0)_54|`` between the posed model's
     projection p and the face;
   - *projection method*: ``E_i = (Q_i - p_i) - (Q_0 - p_0)``: the landmarks' offset
     from the projected posed model, minus the neutral frame's (shape) offset.
3. **Handles**: each landmark vertex, projected to p (pixels) with its camera depth z, is
   moved to ``p + E_i`` in the image plane at the same depth z and mapped back to the mesh
   frame.
   With ``anchors="rim"`` (default) the vertices of the mesh's largest boundary loop (the
   ICT mesh's opening at the back of the head and neck) are extra handles fixed at rest,
   so that regions far from any landmark (scalp, neck) move rigidly with the head instead
   of drifting with the nearest landmarks; ``anchors="none"`` uses the landmarks only.
4. **Laplacian deformation** (:class:`facesynth.mesh.deform.LaplacianDeformer`) of the
   neutral mesh in its own frame; the frame's output is (vertices, R_i, t_i).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.landmarks import POSE_POINTS, RIGID_INNER
from facesynth.mesh.camera import back_project, default_intrinsics, from_camera, project, projection_matrix, to_camera
from facesynth.mesh.deform import DeformInfo, LaplacianDeformer
from facesynth.mesh.io import FaceMesh
from facesynth.mesh.laplacian import boundary_loops
from facesynth.mesh.pose import Pose, solve_pose

#: iBUG indices (0-based) that move little with expression: outline at ear height,
#: nose bridge and base, eye corners. Used for the head pose.
POSE_LANDMARKS = np.array(POSE_POINTS)
#: Inner rigid points used for the 2D similarity alignment of the reference frame.
ALIGN_LANDMARKS = np.array(RIGID_INNER)
MOVEMENTS = ("transformation", "projection")


def umeyama_2d(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``dst ~ s R src + t`` (least squares, Umeyama 1991) for (N, 2) points.

    Returns s (float), R (2, 2) with det +1, t (2,).
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ d @ Vt
    s = float(np.trace(np.diag(S) @ d) / (a**2).sum() * len(src)) if with_scale else 1.0
    return s, R, md - s * R @ ms


@dataclass
class TransferConfig:
    """Options of :class:`Transfer` (see the CLI for their meaning)."""

    method: str = "plain"
    constraints: str = "hard"
    weight: float = 1.0
    pose_method: str = "epnp"
    fov_deg: float = 40.0
    movement: str = "transformation"
    tol: float = 1e-3
    max_iter: int = 30
    anchors: str = "rim"


@dataclass
class FrameResult:
    """One transferred frame: deformed vertices (V, 3) in the mesh frame, the pose, the
    handle targets (H, 3) in the mesh frame and the deformation info."""

    vertices: np.ndarray
    pose: Pose
    targets: np.ndarray
    info: DeformInfo


class Transfer:
    """Drive ``mesh`` with landmarks of a video of size ``image_size`` = (width, height).

    Parameters
    ----------
    mesh : FaceMesh (neutral).
    landmark_map : int (68,) iBUG -> vertex, -1 for landmarks the mesh lacks.
    image_size : (width, height) of the frames the landmarks come from.
    config : TransferConfig.
    K : (3, 3) intrinsics; default :func:`default_intrinsics` with ``config.fov_deg``.
    """

    def __init__(self, mesh: FaceMesh, landmark_map: np.ndarray, image_size, config: TransferConfig | None = None,
                 K: np.ndarray | None = None, pose_filter=None):
        self.mesh = mesh
        self.cfg = config or TransferConfig()
        if self.cfg.movement not in MOVEMENTS:
            raise FacesynthError(f"transfer: movement must be one of {MOVEMENTS}, got {self.cfg.movement!r}")
        lmap = np.asarray(landmark_map, np.int64)
        self.lm_idx = np.flatnonzero(lmap >= 0)
        self.handles = lmap[self.lm_idx]
        self.pose_idx = np.intersect1d(POSE_LANDMARKS, self.lm_idx)
        if len(self.pose_idx) < 6:
            raise FacesynthError(f"transfer: the landmark map covers {len(self.pose_idx)} of the pose landmarks, need 6")
        for need in (48, 54):
            if lmap[need] < 0:
                raise FacesynthError("transfer: the landmark map must contain the mouth corners (iBUG 49 and 55)")
        self.lmap = lmap
        self.K = default_intrinsics(*image_size, self.cfg.fov_deg) if K is None else np.asarray(K, float)
        if self.cfg.anchors not in ("rim", "none"):
            raise FacesynthError(f"transfer: anchors must be 'rim' or 'none', got {self.cfg.anchors!r}")
        loops = boundary_loops(mesh.faces, len(mesh.vertices)) if self.cfg.anchors == "rim" else []
        self.anchors = np.setdiff1d(loops[0], self.handles) if loops else np.zeros(0, np.int64)
        self.deformer = LaplacianDeformer(
            mesh.vertices, mesh.faces, np.concatenate([self.handles, self.anchors]), self.cfg.method,
            self.cfg.constraints, self.cfg.weight, self.cfg.tol, self.cfg.max_iter,
        )
        self.pose_filter = pose_filter
        self.Q0: np.ndarray | None = None
        self.p0: np.ndarray | None = None

    def pose(self, Q: np.ndarray, t_s: float | None = None) -> Pose:
        """Head pose of the neutral mesh from landmarks Q (68, 2)."""
        X = self.mesh.vertices[self.lmap[self.pose_idx]]
        pose = solve_pose(X, Q[self.pose_idx], self.K, self.cfg.pose_method)
        if self.pose_filter is not None and t_s is not None:
            pose = Pose(*self.pose_filter(pose.R, pose.t, t_s), pose.K)
        return pose

    def set_reference(self, Q0: np.ndarray) -> None:
        """Use landmarks Q0 (68, 2) as the neutral reference frame."""
        Q0 = np.asarray(Q0, float)
        if not np.isfinite(Q0).all():
            raise FacesynthError("transfer: the neutral reference frame has NaN landmarks")
        self.Q0 = Q0
        pose0 = solve_pose(self.mesh.vertices[self.lmap[self.pose_idx]], Q0[self.pose_idx], self.K, self.cfg.pose_method)
        self.p0 = project(pose0.P, self.mesh.vertices[self.handles])

    def movement(self, Q: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Movement vectors (H, 2) in pixels for the mapped landmarks, given the posed
        model's projected handles p (H, 2)."""
        if self.Q0 is None:
            raise FacesynthError("transfer: call set_reference() with the neutral frame first")
        if self.cfg.movement == "projection":
            return (Q[self.lm_idx] - p) - (self.Q0[self.lm_idx] - self.p0)
        s, R, t = umeyama_2d(self.Q0[ALIGN_LANDMARKS], Q[ALIGN_LANDMARKS])
        A = s * self.Q0 @ R.T + t
        E = Q - A
        ratio = np.linalg.norm(p[self.lm_idx == 48][0] - p[self.lm_idx == 54][0]) / np.linalg.norm(A[48] - A[54])
        return ratio * E[self.lm_idx]

    def frame(self, Q: np.ndarray, t_s: float | None = None) -> FrameResult:
        """Transfer one frame of landmarks Q (68, 2) (finite)."""
        Q = np.asarray(Q, float)
        pose = self.pose(Q, t_s)
        Xh = self.mesh.vertices[self.handles]
        Xc = to_camera(pose.R, pose.t, Xh)
        p = project(projection_matrix(pose.K, np.eye(3), np.zeros(3)), Xc)
        targets_c = back_project(pose.K, p + self.movement(Q, p), Xc[:, 2])
        targets = from_camera(pose.R, pose.t, targets_c)
        V, info = self.deformer.deform(np.vstack([targets, self.mesh.vertices[self.anchors]]), return_info=True)
        return FrameResult(V, pose, targets, info)
