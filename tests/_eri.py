"""The small synthetic ERI subject shared by the ERI tests (its fixtures: conftest.py)."""

import numpy as np

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from tests._faces import face_sequence_arrays, face_template, smooth_image

CFG = dict(width=64, neutral_index=0, batch_size=8, compare=[])


def _sequence(n=16, seed=0) -> FaceSequence:
    """Frames of one smooth 'face' whose lower half darkens as the mouth opens."""
    _, lm = face_sequence_arrays(n, seed)
    lm[0] = face_template()
    base = smooth_image(180, 180, seed)
    ys = np.arange(180)[:, None, None]
    frames = []
    for i in range(n):
        open_ = float(lm[i, 57, 1] - lm[i, 51, 1] - (lm[0, 57, 1] - lm[0, 51, 1]))
        gain = 1.0 - 0.02 * open_ * (ys > 120)
        frames.append((np.clip(base * gain, 0, 1) * 255).astype(np.uint8))
    return FaceSequence.from_arrays(lm, ArrayFrames(np.stack(frames)), name="synthetic")
