"""Compositing: pasting a rendered face crop into a frame (numpy + OpenCV, no torch). The one
implementation, in the ground so that every user imports it: the evaluation, ERI's synthesis,
the torch-free runtime (still frames and the avatar's own frame) and the talking-head graph's
reference (:class:`facesynth.onnx.head_parts.SeamGraph` computes the same steps as tensor ops).

:func:`blend_face` pastes one crop: a feathered alpha, and (``match_colour``) the face's colour
matched to the frame's at the seam; :func:`composite` is the still-frame form (feather in frame
pixels, no colour matching) and :func:`blend_rendered` takes a renderer's batch.

The synthesized face and the frame under it differ slightly in colour (the appearance
model's mean, lighting of other training frames), which shows as a seam. ``blend_face``
measures the mean colour difference between the frame and the face in a band just inside
the face's outline and shifts the face by it (the first-order form of Reinhard et al.'s
colour transfer, IEEE CG&A 2001, restricted to the seam), then feathers the edge.

The alpha and the band are made in the rendered crop's own pixels (a few thousand, where
the frame's face box holds ten to a hundred times more), then placed in the frame with
the face, premultiplied (:func:`seam_layers`); the talking-head graph
(:class:`facesynth.onnx.head_parts.SeamGraph`) computes the same steps as tensor ops.
"""

from __future__ import annotations

import cv2
import numpy as np

MIN_BAND = 20.0  # frame pixels of seam band below which the colour is not matched
STILL_FEATHER = 2.0  # frame pixels: the seam of a face composited into a still frame
GREY = 128  # uint8 level of the plain background a face is composited into where no frame is known


def crop_rgb(crops: np.ndarray, i: int = 0) -> np.ndarray:
    """Crop ``i`` of a rendered batch (B, C, H_c, W_c), C 1 or 3, as a contiguous
    (H_c, W_c, 3) image (a grey crop repeated to three channels)."""
    crop = np.ascontiguousarray(crops[i].transpose(1, 2, 0))
    return np.repeat(crop, 3, axis=2) if crop.shape[2] == 1 else crop


def seam_width(mask: np.ndarray) -> float:
    """A feather width (pixels of ``mask``) in proportion to the face: 4% of the mask's larger
    side, >= 2."""
    ys, xs = np.nonzero(mask > 0.5)
    if not len(ys):
        return 2.0
    return max(2.0, 0.04 * float(max(np.ptp(ys), np.ptp(xs))))


def _feather(mask: np.ndarray, feather: float | None) -> float:
    """The feather in crop pixels: ``feather`` if given, else :func:`seam_width` of the mask."""
    return float(feather) if feather is not None else seam_width(mask)


def gaussian_kernel(sigma: float) -> np.ndarray:
    """float32 (k,) OpenCV's Gaussian kernel for ``sigma`` (its float32 size rule, ksize 0)."""
    k = int(round(sigma * 8 + 1)) | 1
    return cv2.getGaussianKernel(k, sigma, cv2.CV_32F).reshape(-1)


def _erode(hard: np.ndarray, r: int) -> np.ndarray:
    """Square (2r + 1) erosion of a uint8 {0, 1} map, the outside of the map counted as 0."""
    return cv2.erode(hard, np.ones((2 * r + 1, 2 * r + 1), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)


def seam_layers(mask: np.ndarray, feather: float) -> tuple[np.ndarray, np.ndarray]:
    """The seam in the crop's pixels: float32 (H_c, W_c) alpha and band.

    alpha: the mask (> 0.5) eroded by ``ceil(feather)`` pixels (a square), blurred by a
    Gaussian of sigma ``feather / 2`` and cut to the mask; band: the mask less its erosion by
    twice that (where the colours are compared). Outside the crop counts as outside the
    mask: a face that reaches the crop's edge (a head turned far) fades out there too, where
    it used to end in a hard line."""
    hard = (np.asarray(mask) > 0.5).astype(np.uint8)
    r = max(1, int(np.ceil(feather)))
    inner = _erode(hard, r).astype(np.float32)
    g = gaussian_kernel(feather / 2.0)
    alpha = cv2.sepFilter2D(inner, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT_101) * hard
    band = hard & (_erode(hard, 2 * r) == 0)
    return alpha, band.astype(np.float32)


def blend_face(crop: np.ndarray, mask: np.ndarray, placement: np.ndarray, background: np.ndarray,
               feather: float | None = None, match_colour: bool = True) -> np.ndarray:
    """Paste a rendered crop into ``background``.

    crop : float32 (H_c, W_c, 3) in [0, 1]; mask : float32 (H_c, W_c); placement : (2, 3)
    crop -> frame; background : uint8 (H, W, 3); feather : soft edge in the crop's pixels
    (default :func:`seam_width` of the mask); match_colour : shift the face's colour by the
    frame's mean less the face's in the seam band. Returns uint8 (H, W, 3):
    ``face * alpha + shift * alpha + frame * (1 - alpha)`` with alpha and the premultiplied
    face placed bilinearly, rounded.
    """
    h, w = background.shape[:2]
    ch, cw = mask.shape
    out = background.copy()
    # work in the placed crop's bounding box (warping the whole frame costs milliseconds)
    corners = np.array([[0, 0, 1], [cw, 0, 1], [0, ch, 1], [cw, ch, 1]], np.float64) @ np.asarray(placement, np.float64).T
    x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int) - 2, 0)
    x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 2, [w, h])
    if x1 <= x0 or y1 <= y0:
        return out
    alpha, band = seam_layers(mask, _feather(mask, feather))
    crop = np.asarray(crop, np.float32)
    m = np.asarray(placement, np.float64).copy()
    m[:, 2] -= (x0, y0)
    size = (int(x1 - x0), int(y1 - y0))
    face = cv2.warpAffine(crop * alpha[..., None], m, size, flags=cv2.INTER_LINEAR)
    a_b = cv2.warpAffine(np.dstack([alpha, band]), m, size, flags=cv2.INTER_LINEAR)
    a, b = a_b[..., 0:1], a_b[..., 1]
    bg = background[y0:y1, x0:x1].astype(np.float32) / 255.0
    if match_colour and b.sum() > MIN_BAND:
        face_mean = (crop * band[..., None]).sum((0, 1)) / band.sum()
        face = face + a * ((bg * b[..., None]).sum((0, 1)) / b.sum() - face_mean)
    blended = face + (1.0 - a) * bg
    out[y0:y1, x0:x1] = np.clip(np.floor(blended * 255.0 + 0.5), 0, 255).astype(np.uint8)
    return out


def placed_alpha(mask: np.ndarray, placement: np.ndarray, size: tuple[int, int], feather: float | None = None) -> np.ndarray:
    """float32 (H, W) the alpha with which :func:`blend_face` composites a face of ``mask``
    (H_c, W_c) placed by ``placement`` (2, 3) into a frame of ``size`` (W, H): where, and how
    much, the rendered face replaces the frame (e.g. to composite another image with it)."""
    alpha, _ = seam_layers(mask, _feather(mask, feather))
    return cv2.warpAffine(alpha, np.asarray(placement, np.float64), tuple(int(v) for v in size), flags=cv2.INTER_LINEAR)


def blend_rendered(crops: np.ndarray, masks: np.ndarray, placements: np.ndarray, background: np.ndarray, i: int = 0,
                   feather: float | None = None, match_colour: bool = True, still: bool = False) -> np.ndarray:
    """Face ``i`` of a renderer's batch (``Renderer.render`` / ``FaceModel.render`` outputs:
    crops (B, C, H_c, W_c), masks (B, 1, H_c, W_c), placements (B, 2, 3)) pasted into
    ``background`` with :func:`blend_face` -> uint8 (H, W, 3); ``still``: as :func:`composite`
    (``feather`` in frame pixels, default :data:`STILL_FEATHER`; no colour matching)."""
    crop, mask, placement = crop_rgb(crops, i), masks[i, 0], np.asarray(placements[i], np.float64)
    if still:
        return composite(crop, mask, placement, background, STILL_FEATHER if feather is None else feather)
    return blend_face(crop, mask, placement, background, feather, match_colour)


def crop_scale(placement: np.ndarray) -> float:
    """Frame pixels per crop pixel of a (2, 3) crop -> frame ``placement`` (its linear part's
    area scale, square-rooted)."""
    return float(np.sqrt(abs(np.linalg.det(np.asarray(placement, np.float64)[:, :2]))))


def composite(crop: np.ndarray, mask: np.ndarray, placement: np.ndarray, background: np.ndarray,
              feather: float = STILL_FEATHER) -> np.ndarray:
    """Paste a rendered crop into a still frame: :func:`blend_face` without colour matching,
    ``feather`` (> 0) in frame pixels (converted to the crop's by the placement's scale).

    crop : float32 (H_c, W_c, 3) in [0, 1]; mask : float32 (H_c, W_c) in [0, 1]; placement :
    (2, 3) crop -> frame; background : uint8 (H, W, 3). Returns uint8 (H, W, 3)."""
    return blend_face(crop, mask, placement, background, feather / crop_scale(placement), match_colour=False)
