"""The neutral frame of a sequence: one rule for every part that needs one (the ERI model,
the 3D transfer, the reenactment's driver and the exported avatar): among frames with a
closed mouth, the one closest to the mean shape. Numpy only (the torch-free runtime uses it).

Points are (x, y) pixels, iBUG-68 landmarks (N, 68, 2); :func:`select_neutral` also takes
another registered scheme's (N, P, 2) and decides on their iBUG-68 view.
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.geometry import generalised_procrustes
from facesynth.landmarks import INNER_LOWER, INNER_UPPER, MOUTH_CLOSED, ibug68_view, mouth_open, scheme_for_points

__all__ = ["INNER_LOWER", "INNER_UPPER", "MOUTH_CLOSED", "NEUTRAL_FRAMES", "OnlineNeutral", "mouth_open", "select_neutral"]

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
