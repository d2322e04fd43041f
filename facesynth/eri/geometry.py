"""Geometry of the ERI model: choosing the neutral frame, forehead points that follow the
head rigidly, and the model's (neutral) geometry with an optionally opened mouth.

Points are (x, y) pixels; "extended" landmarks are the 68 iBUG points followed by
``N_FOREHEAD`` forehead points (one above each brow point 17-26).
"""

from __future__ import annotations

import numpy as np

from facesynth.eri.faps import face_axes, head_pose
from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, similarity_fit
from facesynth.landmarks import BROWS, EYES, N_LANDMARKS, inter_ocular
from facesynth.model.procrustes import generalised_procrustes

N_FOREHEAD = 10
INNER_UPPER = (61, 62, 63)  # inner-lip points facing INNER_LOWER across the mouth opening
INNER_LOWER = (67, 66, 65)


def mouth_open(landmarks: np.ndarray) -> np.ndarray:
    """Mean inner-lip gap (61-67, 62-66, 63-65) / inter-ocular distance: (N, 68, 2) -> (N,)."""
    lm = np.asarray(landmarks, np.float64)
    gap = np.linalg.norm(lm[..., list(INNER_UPPER), :] - lm[..., list(INNER_LOWER), :], axis=-1).mean(-1)
    return gap / inter_ocular(lm)


def select_neutral(landmarks: np.ndarray, mouth_closed_max: float = 0.03) -> tuple[int, dict]:
    """Automatic neutral frame: closest (Procrustes distance) to the mean shape among frames
    whose mouth is closed (``mouth_open <= mouth_closed_max``; if none is, the 10% of
    frames with the smallest gap).

    Parameters
    ----------
    landmarks : (N, 68, 2) candidate frames (e.g. the training rows).

    Returns
    -------
    index : int, row into ``landmarks``
    info : dict with the distance, the mouth gap and the number of candidates (for the artifact).
    """
    lm = np.asarray(landmarks, np.float64)
    if lm.ndim != 3 or len(lm) < 1:
        raise FacesynthError(f"neutral selection needs (N, 68, 2) landmarks, got {lm.shape}")
    gap = mouth_open(lm)
    cand = np.flatnonzero(gap <= mouth_closed_max)
    rule = f"mouth_open <= {mouth_closed_max}"
    if len(cand) == 0:
        cand = np.argsort(gap)[: max(1, len(lm) // 10)]
        rule = "10% smallest mouth gap (no frame under the threshold)"
    aligned, mean = generalised_procrustes(lm) if len(lm) > 1 else (lm, lm[0])
    dist = np.linalg.norm((aligned - mean).reshape(len(lm), -1), axis=1)
    best = int(cand[np.argmin(dist[cand])])
    return best, {"rule": rule, "candidates": int(len(cand)), "procrustes_distance": float(dist[best]),
                  "mouth_open": float(gap[best])}


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
