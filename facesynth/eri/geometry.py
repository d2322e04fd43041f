"""Geometry of the ERI model: choosing the neutral frame, forehead points that follow the
head rigidly, and the model's (neutral) geometry with an optionally opened mouth.

Points are (x, y) pixels; "extended" landmarks are the 68 iBUG points followed by
``N_FOREHEAD`` forehead points (one above each brow point 17-26).
"""

from __future__ import annotations

import numpy as np

from facesynth.eri.faps import face_axes, head_pose
from facesynth.geometry import apply_affine, similarity_fit
from facesynth.landmarks import BROWS, EYES, N_LANDMARKS, inter_ocular
from facesynth.neutral import INNER_LOWER, INNER_UPPER, mouth_open, select_neutral

# the neutral-frame choice is shared with the 3D transfer and the reenactment (facesynth.neutral)
__all__ = ["INNER_LOWER", "INNER_UPPER", "mouth_open", "select_neutral", "N_FOREHEAD", "forehead_points", "extend",
           "open_mouth", "upright", "to_canvas"]

N_FOREHEAD = 10
def forehead_points(neutral: np.ndarray, fraction: float) -> np.ndarray:
    """(N_FOREHEAD, 2) points above the brows of a (68, 2) neutral face, ``fraction`` of the
    pupil-line-to-chin distance up the face's vertical axis."""
    neutral = np.asarray(neutral, np.float64)
    down = face_axes(neutral)[1]
    eyes = neutral[list(EYES)].mean(0)
    height = fraction * float((neutral[8] - eyes) @ down)
    return neutral[list(BROWS)] - height * down


def extend(landmarks: np.ndarray, neutral: np.ndarray, forehead: np.ndarray) -> np.ndarray:
    """Append forehead points: (N, 68, 2) frames -> (N, 68 + N_FOREHEAD, 2) float32.

    The neutral face's ``forehead`` points follow each frame's head pose (similarity
    fitted on rigid points), so brow motion stretches the skin between brows and forehead.
    """
    lm = np.asarray(landmarks, np.float64)
    if lm.ndim == 2:
        lm = lm[None]
    if len(forehead) == 0:
        return lm.astype(np.float32)
    fh = apply_affine(np.asarray(forehead, np.float64)[None], head_pose(lm, neutral))
    return np.concatenate([lm, fh], 1).astype(np.float32)


def open_mouth(points: np.ndarray, gap: float) -> np.ndarray:
    """Open the inner lips of (P >= 68, 2) points by ``gap`` x inter-ocular distance (upper
    inner lip up, lower down, middles fully and side points by 70%); corners stay."""
    pts = np.asarray(points, np.float64).copy()
    if gap <= 0:
        return pts
    down = face_axes(pts[:N_LANDMARKS])[1]
    step = 0.5 * gap * inter_ocular(pts[:N_LANDMARKS])
    for idx, w in zip((61, 62, 63), (0.7, 1.0, 0.7), strict=True):
        pts[idx] -= w * step * down
    for idx, w in zip((67, 66, 65), (0.7, 1.0, 0.7), strict=True):
        pts[idx] += w * step * down
    return pts


def upright(points: np.ndarray) -> np.ndarray:
    """Rotate (P, 2) points about their centroid so that the eye axis is horizontal."""
    x = face_axes(np.asarray(points, np.float64)[:N_LANDMARKS])[0]
    c = np.asarray(points, np.float64).mean(0)
    rot = np.array([[x[0], x[1]], [-x[1], x[0]]])
    return (np.asarray(points, np.float64) - c) @ rot.T + c


def to_canvas(points: np.ndarray, ref_points: np.ndarray, pad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Similarity-map (N, P, 2) frame points onto the model geometry (least squares over all
    points), shifted by ``pad`` pixels. Returns canvas points (N, P, 2) float32 and the
    (N, 2, 3) frame -> canvas transforms."""
    pts = np.asarray(points, np.float64)
    m = similarity_fit(pts, np.asarray(ref_points, np.float64)[None])
    m[..., 2] += pad
    return apply_affine(pts, m).astype(np.float32), m
