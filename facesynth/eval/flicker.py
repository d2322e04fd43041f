"""Temporal flicker of the rendered face (``flicker_frame_common`` of ``metrics.json``).

On ``n`` consecutive held-out frames from the middle of the test segment, the face is
rendered from each frame's landmarks (sigma 0) and pasted into its real frame as for
``psnr_frame`` (feathered, no colour match). The flicker of a sequence of frames is its mean
absolute frame-to-frame change (0-255 per channel) over the common region (the dlib hull 0-26
eroded 3 px, :mod:`facesynth.eval.common_region`) of both frames of each pair, pooled over the
pairs. The real frames' flicker is the motion a face really has; the ratio ``rendered / real``
is what a viewer sees added (> 1: the rendered face changes more than the real one, e.g.
popping texture) or removed (< 1: a face that moves less than it should).
"""

from __future__ import annotations

import numpy as np

from facesynth.compositing import composite
from facesynth.eval.common_region import hull_box, region_masks
from facesynth.eval.frame_level import MARGIN


def flicker_rows(n_test: int, n: int) -> np.ndarray:
    """Positions (into the test rows) of ``n`` consecutive frames centred in the test segment."""
    n = min(n, n_test)
    start = max(0, (n_test - n) // 2)
    return start + np.arange(n)


def flicker(model, textures: dict[str, np.ndarray], seq, rows: np.ndarray, common: np.ndarray, feather: float) -> dict:
    """{"real": px, row: px for each of ``textures``, "ratio": {row: row / real}, "frames": n}.

    textures : {row name: (n, C * M) textures of ``rows``}; rows : (n,) consecutive sequence
    rows; common : (n, 68, 2) their dlib landmarks."""
    n_model = model.mean_shape.shape[0]
    lm = seq.landmarks[rows][:, :n_model]
    rendered = {name: model.render(t, lm) for name, t in textures.items()}
    frames = list(seq.iter_frames(rows))
    h, w = frames[0].shape[:2]
    sums = {name: 0.0 for name in ["real", *textures]}
    count = 0
    prev = None
    for j, frame in enumerate(frames):
        box = hull_box(common[j], (h, w), MARGIN)
        shown = {"real": frame}
        for name, (img, msk, plc) in rendered.items():
            shown[name] = composite(img[j], msk[j], plc[j], frame, feather)
        mask = np.zeros((h, w), bool)
        y0, y1, x0, x1 = box
        mask[y0:y1, x0:x1] = region_masks(common[j], box)["whole"]
        if prev is not None:
            both = mask & prev[0]
            for name, img in shown.items():
                sums[name] += float(np.abs(img[both].astype(np.int16) - prev[1][name][both]).sum())
            count += 3 * int(both.sum())
        prev = (mask, shown)
    out = {name: v / max(count, 1) for name, v in sums.items()}
    out["ratio"] = {name: out[name] / out["real"] if out["real"] > 0 else float("nan") for name in textures}
    out["frames"] = len(rows)
    return out
