"""Temporal splits. Neighbouring video frames are near duplicates, so a random frame
split leaks the test set into training; facesynth offers only temporal splits."""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError

TRAIN_FRACTION = 0.75  # the default share of leading frames that trains (data.train_fraction)


def temporal_split(n: int, train_fraction: float = TRAIN_FRACTION, gap: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Split ``n`` consecutive frames into a leading training part and a trailing test part.

    Parameters
    ----------
    n : int
        Number of frames.
    train_fraction : float
        Fraction of frames (from the start) used for training, in (0, 1).
    gap : int
        Frames dropped between the two parts, so that the first test frame is not a
        near copy of the last training frame.

    Returns
    -------
    train, test : np.ndarray
        int64 row indices, shapes (n_train,) and (n_test,).
    """
    if not 0.0 < train_fraction < 1.0:
        raise FacesynthError(f"train_fraction must be in (0, 1), got {train_fraction}")
    if gap < 0:
        raise FacesynthError(f"gap must be >= 0, got {gap}")
    n_train = int(round(n * train_fraction))
    test_start = n_train + gap
    if n_train < 2 or test_start >= n:
        raise FacesynthError(
            f"cannot split {n} frames with train_fraction={train_fraction} and gap={gap}: "
            "need at least 2 training and 1 test frame"
        )
    return np.arange(n_train), np.arange(test_start, n)
