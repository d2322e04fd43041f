"""The data a training run names (``data.*`` of ``train.py``'s config): a stage's config
dataclass, as :class:`facesynth.eri.config.EriConfig` is ERI's, so that the run folder's
reader (:mod:`facesynth.rundir`) checks it below the training layer."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from facesynth.data.smoothing import FAST_RADII_S, LIGHT_SHIFT_PX
from facesynth.data.splits import TRAIN_FRACTION


@dataclass
class DataConf:
    """kind: 'synthetic' (the embedded default subject) or 'video' (``path``: a folder in
    the ingest layout, a folder of images + .pts, or .npy/.npz). Temporal split:
    the first ``train_fraction`` trains, the rest (after ``gap`` frames) tests.
    ``smooth_landmarks``: smooth a video's tracked landmarks along time, zero phase, each part
    of the split alone (:mod:`facesynth.data.smoothing`), for training and evaluation alike; the
    synthetic subject's landmarks are exact and never smoothed. ``smooth_fast_radii_s``: the
    point speed (face radii per second) from which the smoothing's light filter alone applies;
    ``smooth_light_shift_px``: the most it moves the face's centroid (frame px; None: no limit)."""

    kind: str = "synthetic"
    path: Optional[str] = None
    n_frames: int = 240
    size: int = 256
    max_frames: Optional[int] = None
    train_fraction: float = TRAIN_FRACTION
    gap: int = 0
    smooth_landmarks: bool = True
    smooth_fast_radii_s: float = FAST_RADII_S
    smooth_light_shift_px: Optional[float] = LIGHT_SHIFT_PX
