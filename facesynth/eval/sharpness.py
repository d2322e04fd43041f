"""How much of the real frame's detail a rendered face keeps (``sharpness_frame_common`` of
``metrics.json``), beside PSNR, which barely moves when a face turns waxy.

Sharpness of a rendered frame against the real one, over a region::

    S = sum_region |Sobel(rendered)|^2 / sum_region |Sobel(real)|^2

with ``cv2.Sobel`` (3x3, x and y, each colour channel, float32) of the whole frame, summed
over the region's pixels and the channels. The rendered face is pasted into the real frame
with :func:`facesynth.compositing.blend_face` (as the app shows it), so S is measured on
what a viewer sees; the regions are the common region's (the dlib hull 0-26 eroded 3 px and
its parts, :mod:`facesynth.eval.common_region`), identical for every landmark scheme. S = 1:
as much gradient energy as the real frame; a blurred face scores < 1. Energy ratios, not
correlations: a face with the right amount of detail in the wrong place also scores ~1, so
S is read beside PSNR, never instead of it. Per frame, then the median over the frames
evaluated (robust to the odd frame with motion blur in the real one).
"""

from __future__ import annotations

import cv2
import numpy as np


def gradient_energy(image: np.ndarray) -> np.ndarray:
    """float64 (H, W) Sobel gradient energy per pixel, summed over channels, of an (H, W, C)
    or (H, W) image (uint8 or float; the scale is the input's)."""
    img = np.asarray(image, np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    e = gx.astype(np.float64) ** 2 + gy.astype(np.float64) ** 2
    return e.sum(-1) if e.ndim == 3 else e


def sharpness(rendered: np.ndarray, real: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, float]:
    """{region: S} of ``rendered`` against ``real`` (same-shape images) over each bool mask of
    ``masks`` (NaN where the real frame has no gradient energy there)."""
    er, ef = gradient_energy(rendered), gradient_energy(real)
    out = {}
    for name, m in masks.items():
        den = float(ef[m].sum())
        out[name] = float(er[m].sum() / den) if den > 0 else float("nan")
    return out


def median_table(per_frame: dict[str, dict[str, list[float]]]) -> dict[str, dict[str, float]]:
    """{row: {region: [S per frame]}} -> {region: {row: median S}} (NaN frames left out)."""
    regions = next(iter(per_frame.values())).keys() if per_frame else []
    return {reg: {row: float(np.nanmedian(v[reg])) if np.isfinite(v[reg]).any() else float("nan")
                  for row, v in per_frame.items()} for reg in regions}
