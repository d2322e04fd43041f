"""Expression ratio images (ERI).

Z. Liu, Y. Shan, Z. Zhang, "Expressive expression mapping with ratio images",
SIGGRAPH 2001: with the face warped to a common geometry, the per-pixel ratio
R = F_expr / F_neutral captures illumination changes caused by skin deformation
(wrinkles, creases, shading); multiplying another face's neutral image by R transfers them.

Here frames are warped to the model's neutral geometry (``facesynth.model.warp.ToReference``)
and ratios are taken per pixel and channel at the M pixels of its mask:

    R_i = clip((F_i + eps) / (F_0 + eps), 1 / clip, clip)

optionally Gaussian-filtered inside the mask (normalised convolution, so the mask edge
does not darken), and stored as log R (default) or R.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from facesynth.model.warp import ToReference


def sample_textures(images: np.ndarray, points: np.ndarray, sampler: ToReference) -> torch.Tensor:
    """uint8 (B, H, W, 3) images + (B, P, 2) points -> float32 (B, 3, M) textures in [0, 1]."""
    x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)
    with torch.no_grad():
        return sampler(x, torch.from_numpy(np.asarray(points, np.float32)))


def gaussian_in_mask(values: torch.Tensor, sampler: ToReference, sigma: float) -> torch.Tensor:
    """Gaussian filter (B, C, M) mask-pixel values with ``sigma`` (pixels), normalised by the
    filtered mask so that constant fields stay constant up to the mask edge."""
    if sigma <= 0:
        return values
    from kornia.filters import gaussian_blur2d

    k = 2 * math.ceil(3 * sigma) + 1
    img = sampler.to_image(values)
    mask = sampler.to_image(torch.ones_like(values[:1, :1]))
    num = gaussian_blur2d(img, (k, k), (sigma, sigma), border_type="constant")
    den = gaussian_blur2d(mask, (k, k), (sigma, sigma), border_type="constant")
    out = (num / den.clamp_min(1e-8)).flatten(2)
    return out[:, :, sampler.mask_index]


def ratio_images(
    textures: torch.Tensor, neutral: torch.Tensor, sampler: ToReference, eps: float = 0.02,
    clip: float = 4.0, sigma: float = 0.0, log: bool = True,
) -> torch.Tensor:
    """Ratio images of textures against the neutral texture.

    Parameters
    ----------
    textures : (B, C, M) float32 in [0, 1], frames warped to the neutral geometry
    neutral : (C, M) float32, the neutral frame's texture F_0
    sampler : the ToReference of the geometry (for filtering in the image domain)

    Returns
    -------
    torch.Tensor
        (B, C, M) float32: log R (``log``) or R. The neutral frame gives exactly 0 (1).
    """
    r = (textures + eps) / (neutral.unsqueeze(0) + eps)
    r = r.clamp(1.0 / clip, clip)
    r = gaussian_in_mask(r, sampler, sigma)
    return torch.log(r) if log else r


def edge_confidence(neutral: torch.Tensor, sampler: ToReference, tau: float) -> torch.Tensor:
    """Per-pixel confidence (M,) in (0, 1] of ratio images: 1 / (1 + (|grad F_0| / tau)^2)
    of the grey neutral texture (Sobel, per pixel, intensities in [0, 1]).

    Where the neutral face has strong edges (eyeliner, brows, lip and eye contours, the
    mask boundary) a one-pixel misregistration already changes the ratio a lot, so such
    ratios say little about expression and transfer badly to another face (Liu et al.
    note the same for their eye/mouth regions); smooth skin, where wrinkles and
    shading appear, keeps confidence ~1. ``tau <= 0`` disables it (all ones).
    """
    if tau <= 0:
        return torch.ones(neutral.shape[-1])
    from kornia.filters import spatial_gradient

    grey = sampler.to_image(neutral.mean(0, keepdim=True).unsqueeze(0))  # (1, 1, H, W)
    g = spatial_gradient(grey, mode="sobel", normalized=True)  # (1, 1, 2, H, W)
    mag = g.pow(2).sum(2).sqrt().flatten(1)[0, sampler.mask_index]
    return 1.0 / (1.0 + (mag / tau) ** 2)


def to_multiplier(
    values: torch.Tensor, log: bool, clip: float, confidence: torch.Tensor | None = None, bright: float | None = None,
) -> torch.Tensor:
    """Stored ratio values (log R or R) -> multiplicative R in [1/clip, min(clip, bright)];
    with a ``confidence`` (M,), R is pulled towards 1 (log R x c, or 1 + c (R - 1)).

    ``bright`` caps brightening separately: on another face, a ratio > 1 learnt where the
    training subject's neutral skin was dark (a lid crease, eye shadow) saturates skin that
    is already bright there (albedo mismatch), while darkening (creases, shading, the mouth
    interior) transfers well.
    """
    if confidence is not None:
        values = values * confidence if log else 1.0 + (values - 1.0) * confidence
    r = torch.exp(values) if log else values
    return r.clamp(1.0 / clip, min(clip, bright or clip))


def apply_ratio(ratio: torch.Tensor, base: torch.Tensor, eps: float = 0.02) -> torch.Tensor:
    """B' = R x (B + eps) - eps (the inverse of the ratio's definition), clipped to [0, 1].

    ratio : (N, C, M); base : (C, M) or (N, C, M) -> (N, C, M).
    """
    return (ratio * (base + eps) - eps).clamp(0.0, 1.0)
