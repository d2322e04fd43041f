"""Piecewise-affine warps as batched tensor ops (exportable to ONNX: no Python loops
over pixels or triangles, no custom ops).

Two directions:

* :class:`ToReference` samples images into the reference frame (training textures).
  The reference geometry is fixed, so every reference pixel's triangle and barycentric
  coordinates are precomputed; a frame is one (M, 68) matmul and one ``grid_sample``.
* :class:`ToTarget` (in :mod:`facesynth.model.warp_target`) warps a reference-frame
  texture onto any target landmark set (rendering). The triangle covering each output
  pixel is found by *scanline coverage counting* down the canvas columns: each mesh edge
  adds a signed triangle code at its column crossings (scatter-add over at most the span
  of its triangles, sized from the training shapes by :func:`candidate_spans`), and a
  cumulative sum down each column yields the covering triangle; each pixel then reads its
  triangle's affine map from per-frame (triangle, column) tables and its bilinear taps
  with flat gathers. Only the landmarks' bounding box is evaluated (every triangle lies in
  it). The cost is a few gathers per box pixel, instead of (pixels x triangles) tests.

Coordinates: (x, y), integer values at pixel centres; ``grid_sample`` uses
``align_corners=True`` so that this matches OpenCV's ``remap``/``warpAffine``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.model.reference import ReferenceFrame
from facesynth.model.warp_target import ToTarget  # noqa: F401  (re-exported)


def to_grid(xy: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Pixel (x, y) -> grid_sample's [-1, 1] coordinates (align_corners=True). Shape kept."""
    h, w = size
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=xy.dtype, device=xy.device)
    return xy * scale - 1.0


class ToReference(nn.Module):
    """Sample images at the reference frame's face pixels.

    Forward
    -------
    images : (B, C, H, W) float tensor
    landmarks : (B, 68, 2) float tensor, (x, y) pixels of ``images``
    returns : (B, C, M) textures at the M mask pixels of the reference frame
    """

    def __init__(self, ref: ReferenceFrame):
        super().__init__()
        tri_index, bary = ref.rasterise()
        flat = np.flatnonzero(tri_index.reshape(-1) >= 0)
        tri = ref.triangles[tri_index.reshape(-1)[flat]]  # (M, 3)
        weights = np.zeros((len(flat), len(ref.points)), np.float32)
        rows = np.arange(len(flat))[:, None]
        np.add.at(weights, (np.broadcast_to(rows, tri.shape), tri), bary.reshape(-1, 3)[flat])
        self.register_buffer("weights", torch.from_numpy(weights))  # (M, 68)
        self.register_buffer("mask_index", torch.from_numpy(flat))  # (M,) into H*W
        self.size = tuple(ref.size)

    @property
    def n_pixels(self) -> int:
        return int(self.mask_index.numel())

    def forward(self, images: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
        src = torch.matmul(self.weights, landmarks)  # (B, M, 2)
        grid = to_grid(src, (images.shape[-2], images.shape[-1])).unsqueeze(1)  # (B, 1, M, 2)
        out = F.grid_sample(images, grid, mode="bilinear", padding_mode="border", align_corners=True)
        return out[:, :, 0, :]

    def to_image(self, textures: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """(B, C, M) textures -> (B, C, H, W) reference images (``fill`` outside the mask)."""
        b, c, _ = textures.shape
        h, w = self.size
        out = textures.new_full((b, c, h * w), fill)
        out[:, :, self.mask_index] = textures
        return out.view(b, c, h, w)


def similarity_to(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """Least-squares similarity (Umeyama, 2D closed form) mapping ``src`` onto ``dst``.

    src : (B, K, 2); dst : (K, 2) or (B, K, 2). Returns (B, 2, 3) with dst ~ src A^T + t.
    """
    mu_s = src.mean(1, keepdim=True)
    mu_d = dst.mean(-2, keepdim=True)
    s = src - mu_s
    d = dst - mu_d
    a = (s * d).sum((1, 2))
    b = (s[..., 0] * d[..., 1] - s[..., 1] * d[..., 0]).sum(1)
    var = (s * s).sum((1, 2))
    sa, sb = a / var, b / var  # scale * cos, scale * sin
    row0 = torch.stack([sa, -sb], -1)
    row1 = torch.stack([sb, sa], -1)
    rot = torch.stack([row0, row1], 1)  # (B, 2, 2)
    t = mu_d.reshape(-1, 1, 2) - torch.matmul(mu_s, rot.transpose(1, 2))  # (B, 1, 2)
    return torch.cat([rot, t.transpose(1, 2)], 2)


def apply_affine_t(points: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """(B, K, 2) points through (B, 2, 3) affine matrices."""
    return torch.matmul(points, m[:, :, :2].transpose(1, 2)) + m[:, :, 2].unsqueeze(1)


def invert_affine_t(m: torch.Tensor) -> torch.Tensor:
    """Inverse of (B, 2, 3) affine matrices (closed-form 2x2 inverse, exportable)."""
    a, b, c, d = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
    det = a * d - b * c
    inv = torch.stack([torch.stack([d, -b], -1), torch.stack([-c, a], -1)], 1) / det[:, None, None]
    t = -torch.matmul(inv, m[:, :, 2:])
    return torch.cat([inv, t], 2)


def candidate_spans(ref: ReferenceFrame, shapes: np.ndarray, safety: float = 1.3, margin: int = 0) -> np.ndarray:
    """Candidate block size of each triangle for :class:`ToTarget`.

    Parameters
    ----------
    ref : ReferenceFrame
    shapes : np.ndarray
        (N, 68, 2) example target shapes in canvas coordinates (e.g. the training shapes
        aligned to the reference frame, and their +-3 sigma extremes).
    safety : float
        Factor on the largest observed bounding box of each triangle.
    margin : int
        Pixels added after the factor: a triangle a few pixels wide (an eyelid, a lip
        corner) varies by more than a share of its width when a driver's eyelid or lip
        moves it by a pixel or two.

    Returns
    -------
    np.ndarray
        int64 (T, 2): (width, height) in pixels.
    """
    pts = np.concatenate([np.asarray(shapes, np.float64).reshape(-1, len(ref.points), 2), ref.points[None]], 0)
    corners = pts[:, ref.triangles]  # (N, T, 3, 2)
    span = np.floor(corners.max(2) - corners.min(2)).max(0) + 2  # largest bbox + rounding
    return (np.ceil(span * safety) + int(margin)).astype(np.int64)
