"""The neutral frame of a sequence: one rule for every part that needs one (the ERI model,
the 3D transfer, the reenactment's driver and the exported avatar): among frames with a
closed mouth, the one closest to the mean shape. Numpy only (the torch-free runtime uses it).

A reenactment carries motion relative to two neutrals, so whatever one frame's eyes happen to
do (a glance, lids half down) would stay in every frame: :func:`typical_eyes` puts a clip's
neutral eyes (lids and irises) where that clip's eyes usually are.

Points are (x, y) pixels, iBUG-68 landmarks (N, 68, 2); :func:`select_neutral` also takes
another registered scheme's (N, P, 2) and decides on their iBUG-68 view.
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.geometry import generalised_procrustes
from facesynth.landmarks import INNER_LOWER, INNER_UPPER, MOUTH_CLOSED, ibug68_view, mouth_open, scheme_for_points
from facesynth.shape_space import eye_patches

__all__ = ["INNER_LOWER", "INNER_UPPER", "MOUTH_CLOSED", "NEUTRAL_FRAMES", "OnlineNeutral", "mouth_open", "select_neutral",
           "typical_eyes"]

NEUTRAL_FRAMES = 30  # one second of a 30 fps driver: long enough to meet a closed-mouth frame


def select_neutral(landmarks: np.ndarray, mouth_closed_max: float = MOUTH_CLOSED) -> tuple[int, dict]:
    """Automatic neutral frame: closest (Procrustes distance) to the mean shape among frames
    whose mouth is closed (``mouth_open <= mouth_closed_max``; if none is, the 10% of
    frames with the smallest gap).

    Parameters
    ----------
    landmarks : (N, P, 2) candidate frames (e.g. the training rows): iBUG-68 points, or
        those of another registered scheme (mapped with its ``to_ibug68``).

    Returns
    -------
    index : int, row into ``landmarks``
    info : dict with the distance, the mouth gap and the number of candidates (for the artifact).
    """
    lm = np.asarray(landmarks, np.float64)
    scheme = scheme_for_points(lm.shape[1]) if lm.ndim == 3 and lm.shape[-1] == 2 else None
    if scheme is None or len(lm) < 1:
        raise FacesynthError(f"neutral selection needs (N, 68, 2) landmarks (or another scheme's (N, P, 2)), got {lm.shape}")
    lm = ibug68_view(lm)
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


def eye_coordinates(landmarks: np.ndarray, a: int, b: int, points: np.ndarray) -> np.ndarray:
    """(..., P, 2) landmarks -> (..., len(points), 2): each point in its eye's frame, (along,
    across) the corner-to-corner vector from corner ``a`` to ``b``, in units of its length
    (a similarity of the face leaves them unchanged)."""
    lm = np.asarray(landmarks, np.float64)
    e = lm[..., b, :] - lm[..., a, :]
    n2 = (e ** 2).sum(-1)[..., None]
    perp = np.stack([-e[..., 1], e[..., 0]], -1)
    v = lm[..., points, :] - lm[..., a, None, :]
    return np.stack([(v * e[..., None, :]).sum(-1) / n2, (v * perp[..., None, :]).sum(-1) / n2], -1)


def typical_eyes(neutral: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """``neutral`` (P, 2) with each eye's points (lids, iris) at the median over ``landmarks``
    (N, P, 2; rows with NaN left out) of their :func:`eye_coordinates`, placed on the neutral's
    own eye corners; every other point, the corners included, unchanged. Float64 (P, 2).

    Motion is carried relative to a neutral (:mod:`facesynth.retarget`): lp_d6 (MediaPipe)
    driven by its own clip, its avatar's and its driver's neutral frames look 0.09-0.14 eye
    widths apart, and every retargeted frame kept that offset; with each neutral's eyes at its
    clip's typical place the offset is under 0.006 (median 0.002)."""
    n = np.asarray(neutral, np.float64)
    lm = np.asarray(landmarks, np.float64)
    scheme = scheme_for_points(n.shape[0]) if n.ndim == 2 and n.shape[1] == 2 else None
    if scheme is None or lm.ndim != 3 or lm.shape[1:] != n.shape:
        raise FacesynthError(f"typical_eyes: a (P, 2) neutral and (N, P, 2) landmarks of one scheme are needed, "
                             f"got {n.shape} and {lm.shape}")
    lm = lm[np.isfinite(lm).all((1, 2))]
    out = n.copy()
    if not len(lm):
        return out
    for pts, a, b in eye_patches(scheme):
        uv = np.median(eye_coordinates(lm, a, b, pts), 0)  # (len(pts), 2)
        e = n[b] - n[a]
        out[pts] = n[a] + uv[:, :1] * e + uv[:, 1:] * np.array([-e[1], e[0]])
    return out


class OnlineNeutral:
    """A live driver's neutral, chosen while it plays: :func:`select_neutral` among the frames
    seen so far, until ``frames`` have been seen; then the choice stays (the reenactment's
    :class:`~facesynth.runtime.reenact.Reenactor` and the talking head's
    :class:`~facesynth.runtime.talking_head.TalkingHead` without a given neutral)."""

    def __init__(self, frames: int = NEUTRAL_FRAMES):
        if int(frames) < 1:
            raise FacesynthError(f"neutral_frames must be >= 1, got {frames}")
        self.frames = int(frames)
        self._seen: list[np.ndarray] | None = []

    @property
    def choosing(self) -> bool:
        """True until ``frames`` frames have been seen."""
        return self._seen is not None

    def see(self, landmarks: np.ndarray) -> np.ndarray:
        """One more driver frame (P, 2) while :attr:`choosing`; returns the neutral chosen so far."""
        if self._seen is None:
            raise FacesynthError("OnlineNeutral: the neutral is chosen already")
        self._seen.append(landmarks)
        chosen = self._seen[select_neutral(np.stack(self._seen))[0]]
        if len(self._seen) >= self.frames:
            self._seen = None
        return chosen
