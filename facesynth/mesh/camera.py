"""Camera conventions, written down once for the whole ``facesynth.mesh`` package.

Frames
------
**Mesh (model) frame** (the ICT face and most face meshes): x to the viewer's right
(the subject's right eye is at -x), **y up**, **+z towards the viewer**; units cm.

**Camera frame** (OpenCV / Hartley-Zisserman): x right, **y down**, **z forward**
(the direction the camera looks); a point is in front of the camera when z > 0.

**Image**: pixel (u, v) with u to the right and **v down**, origin at the centre of
the top-left pixel; ``[u, v, 1]^T ~ K X_c``.

Pose
----
A pose (R, t) maps mesh coordinates to camera coordinates, ``X_c = R X_m + t``, so the
projection matrix is ``P = K [R | t]`` (3, 4) and the camera centre in mesh
coordinates is ``C = -R^T t``. A face seen straight on, upright, has
``R = MESH_TO_CAMERA = diag(1, -1, -1)`` (y and z flipped: y up -> down, +z towards the
viewer -> towards the camera, i.e. -z forward). The head rotation in the mesh's own
frame is therefore ``R_head = MESH_TO_CAMERA @ R`` (identity for a frontal face), and
:func:`head_euler_deg` reports it as yaw / pitch / roll.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: Rotation taking the mesh frame (y up, +z to viewer) to the camera frame of a frontal,
#: upright view (y down, z forward). Its own inverse.
MESH_TO_CAMERA = np.diag([1.0, -1.0, -1.0])


def intrinsics(f: float, cx: float, cy: float, fy: float | None = None) -> np.ndarray:
    """Pinhole intrinsics K (3, 3) with focal lengths (pixels) and principal point."""
    return np.array([[f, 0.0, cx], [0.0, f if fy is None else fy, cy], [0.0, 0.0, 1.0]])


def default_intrinsics(width: int, height: int, fov_deg: float = 40.0) -> np.ndarray:
    """K (3, 3) for a ``width`` x ``height`` image with horizontal field of view ``fov_deg``.

    Used for real clips whose calibration is unknown: the principal point is the image
    centre, pixels are square, ``f = (width / 2) / tan(fov / 2)``.
    """
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return intrinsics(f, (width - 1) / 2.0, (height - 1) / 2.0)


def projection_matrix(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """P = K [R | t], shape (3, 4)."""
    return np.asarray(K, float) @ np.hstack([np.asarray(R, float), np.reshape(t, (3, 1))])


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Project points X (N, 3) with P (3, 4) -> pixels (N, 2)."""
    X = np.asarray(X, float)
    x = X @ P[:, :3].T + P[:, 3]
    return x[:, :2] / x[:, 2:3]


def to_camera(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Mesh -> camera coordinates, ``X_c = R X + t``; X (..., 3)."""
    return np.asarray(X) @ np.asarray(R).T + np.asarray(t).reshape(3)


def from_camera(R: np.ndarray, t: np.ndarray, Xc: np.ndarray) -> np.ndarray:
    """Camera -> mesh coordinates, ``X = R^T (X_c - t)``; Xc (..., 3)."""
    return (np.asarray(Xc) - np.asarray(t).reshape(3)) @ np.asarray(R)


def back_project(K: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) that project to pixels ``uv`` (N, 2) at depths ``z`` (N,)."""
    uv = np.asarray(uv, float)
    ray = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T
    return ray * (np.asarray(z, float) / ray[:, 2])[:, None]


def head_rotation(R: np.ndarray) -> np.ndarray:
    """Head rotation in the mesh frame (identity when frontal) from a pose rotation R."""
    return MESH_TO_CAMERA @ np.asarray(R, float)


def pose_rotation(R_head: np.ndarray) -> np.ndarray:
    """Inverse of :func:`head_rotation`: pose R = MESH_TO_CAMERA @ R_head."""
    return MESH_TO_CAMERA @ np.asarray(R_head, float)


def head_euler_deg(R: np.ndarray) -> np.ndarray:
    """(yaw, pitch, roll) in degrees of the head rotation of pose R.

    Yaw is about the mesh's y (up) axis, pitch about x, roll about z (intrinsic Y-X-Z).
    """
    return Rotation.from_matrix(head_rotation(R)).as_euler("YXZ", degrees=True)


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Geodesic angle (degrees) between two rotations (3, 3)."""
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
