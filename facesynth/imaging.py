"""Pasting a rendered face crop into a frame (numpy + OpenCV, no torch).

This is the one implementation of compositing, upstream of both users: the torch-side
evaluation (:mod:`facesynth.eval`, :mod:`facesynth.eri`) and the torch-free runtime
(:class:`facesynth.runtime.Renderer`) import it from here.
"""

from __future__ import annotations

import cv2
import numpy as np

STILL_FEATHER = 2.0  # frame pixels: the seam of a face composited into a still frame
GREY = 128  # uint8 level of the plain background a face is composited into where no frame is known


def crop_rgb(crops: np.ndarray, i: int = 0) -> np.ndarray:
    """Crop ``i`` of a rendered batch (B, C, H_c, W_c), C 1 or 3, as a contiguous
    (H_c, W_c, 3) image (a grey crop repeated to three channels)."""
    crop = np.ascontiguousarray(crops[i].transpose(1, 2, 0))
    return np.repeat(crop, 3, axis=2) if crop.shape[2] == 1 else crop


def composite(
    crop: np.ndarray, mask: np.ndarray, placement: np.ndarray, background: np.ndarray, feather: float = STILL_FEATHER
) -> np.ndarray:
    """Paste a rendered crop into a frame with a feathered boundary.

    Parameters
    ----------
    crop : float32 (H_c, W_c, 3) in [0, 1]
    mask : float32 (H_c, W_c) in [0, 1]
    placement : (2, 3) crop -> frame affine map
    background : uint8 (H, W, 3) frame
    feather : float
        Width (frame pixels) of the soft edge; the face is shrunk by it before blurring,
        so no background-coloured ring enters the face.

    Returns
    -------
    uint8 (H, W, 3)
    """
    h, w = background.shape[:2]
    face = cv2.warpAffine(crop, placement, (w, h), flags=cv2.INTER_LINEAR)
    alpha = cv2.warpAffine(mask.astype(np.float32), placement, (w, h), flags=cv2.INTER_LINEAR)
    if feather > 0:
        r = int(np.ceil(feather))
        hard = (alpha > 0.999).astype(np.float32)
        alpha = cv2.erode(hard, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        alpha = cv2.GaussianBlur(alpha, (0, 0), feather / 2) * hard
    bg = background.astype(np.float32) / 255.0
    out = alpha[..., None] * np.clip(face, 0, 1) + (1 - alpha[..., None]) * bg
    return np.clip(out * 255.0 + 0.5, 0, 255).astype(np.uint8)
