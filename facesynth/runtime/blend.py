"""Compositing a rendered face into the avatar's own frame: feathered alpha plus colour
matching at the seam (numpy + OpenCV, no torch).

The synthesized face and the frame under it differ slightly in colour (the appearance
model's mean, lighting of other training frames), which shows as a seam. ``blend_face``
measures the mean colour difference between the frame and the face in a band just inside
the face's outline and shifts the face by it (the first-order form of Reinhard et al.'s
colour transfer, IEEE CG&A 2001, restricted to the seam), then feathers the edge.
"""

from __future__ import annotations

import cv2
import numpy as np


def seam_width(mask: np.ndarray) -> float:
    """A feather width (pixels) in proportion to the face: 4% of the mask's larger side, >= 2."""
    ys, xs = np.nonzero(mask > 0.5)
    if not len(ys):
        return 2.0
    return max(2.0, 0.04 * float(max(np.ptp(ys), np.ptp(xs))))


def blend_face(crop: np.ndarray, mask: np.ndarray, placement: np.ndarray, background: np.ndarray,
               feather: float | None = None, match_colour: bool = True) -> np.ndarray:
    """Paste a rendered crop into ``background``.

    crop : float32 (H_c, W_c, 3) in [0, 1]; mask : float32 (H_c, W_c); placement : (2, 3)
    crop -> frame; background : uint8 (H, W, 3); feather : soft edge in frame pixels
    (default :func:`seam_width` of the placed face); match_colour : shift the face's colour
    to the frame's in the seam band. Returns uint8 (H, W, 3).
    """
    h, w = background.shape[:2]
    # work in the face's bounding box in the frame (warping the whole frame costs milliseconds)
    ch, cw = mask.shape
    corners = np.array([[0, 0, 1], [cw, 0, 1], [0, ch, 1], [cw, ch, 1]], np.float64) @ np.asarray(placement, np.float64).T
    x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int) - 2, 0)
    x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 2, [w, h])
    out = background.copy()
    if x1 <= x0 or y1 <= y0:
        return out
    m = np.asarray(placement, np.float64).copy()
    m[:, 2] -= (x0, y0)
    size = (int(x1 - x0), int(y1 - y0))
    face = cv2.warpAffine(crop, m, size, flags=cv2.INTER_LINEAR)
    hard = (cv2.warpAffine(mask.astype(np.float32), m, size, flags=cv2.INTER_LINEAR) > 0.5).astype(np.uint8)
    if not hard.any():
        return out
    f = float(feather) if feather is not None else seam_width(hard)
    r = max(1, int(np.ceil(f)))
    inner = cv2.erode(hard, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    bg = background[y0:y1, x0:x1].astype(np.float32) / 255.0
    if match_colour:
        band = (hard > 0) & (cv2.erode(hard, np.ones((4 * r + 1, 4 * r + 1), np.uint8)) == 0)
        if band.sum() > 20:
            face = face + (bg[band].mean(0) - face[band].mean(0))
    alpha = cv2.GaussianBlur(inner.astype(np.float32), (0, 0), f / 2) * hard
    blended = alpha[..., None] * np.clip(face, 0, 1) + (1 - alpha[..., None]) * bg
    out[y0:y1, x0:x1] = np.clip(blended * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return out
