"""Piecewise-affine warps as batched tensor ops (exportable to ONNX: no Python loops
over pixels or triangles, no custom ops).

Two directions:

* :class:`ToReference` samples images into the reference frame (training textures).
  The reference geometry is fixed, so every reference pixel's triangle and barycentric
  coordinates are precomputed; a frame is one (M, 68) matmul and one ``grid_sample``.
* :class:`ToTarget` warps a reference-frame texture onto any target landmark set
  (rendering). The triangle covering each output pixel is found by *candidate
  scattering*: each triangle owns a fixed block of candidate pixels sized to the
  largest bounding box that triangle takes over the training shapes (times a safety
  factor); candidates inside their triangle scatter their reference coordinates into
  the output grid, then one ``grid_sample`` reads the texture. Its cost is a few
  times the canvas area, instead of (pixels x triangles) for a brute-force test.

Coordinates: (x, y), integer values at pixel centres; ``grid_sample`` uses
``align_corners=True`` so that this matches OpenCV's ``remap``/``warpAffine``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.model.reference import ReferenceFrame

_FAR = -1.0e4  # grid coordinate far outside any image: grid_sample returns zeros there


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


class ToTarget(nn.Module):
    """Warp reference-frame textures onto target landmark sets.

    Parameters
    ----------
    ref : ReferenceFrame
    span : np.ndarray
        int (T, 2): width and height of each triangle's candidate block, from
        :func:`candidate_spans`.
    canvas : (H, W), optional
        Output size; defaults to the reference frame size.

    Forward
    -------
    textures : (B, C, M) float tensor (M reference mask pixels, as from ToReference)
    target : (B, 68, 2) float tensor, landmarks in canvas pixel coordinates
    returns : image (B, C, H, W) with zeros outside the face, mask (B, 1, H, W) in {0, 1}
    """

    def __init__(self, ref: ReferenceFrame, span: np.ndarray, canvas: tuple[int, int] | None = None):
        super().__init__()
        self.canvas = tuple(canvas or ref.size)
        self.ref_size = tuple(ref.size)
        tri = ref.triangles
        span = np.asarray(span, np.int64)
        cand_tri, cand_off = [], []
        for t, (sw, sh) in enumerate(span):
            oy, ox = np.mgrid[0:sh, 0:sw]
            cand_off.append(np.stack([ox.ravel(), oy.ravel()], -1))
            cand_tri.append(np.full(sw * sh, t))
        cand_tri = np.concatenate(cand_tri)
        self.register_buffer("tri", torch.from_numpy(tri))
        self.register_buffer("span", torch.from_numpy(span.astype(np.float32)))
        self.register_buffer("cand_tri", torch.from_numpy(cand_tri))
        self.register_buffer("cand_off", torch.from_numpy(np.concatenate(cand_off).astype(np.float32)))
        self.register_buffer("cand_ref", torch.from_numpy(ref.points[tri[cand_tri]].astype(np.float32)))  # (Nc, 3, 2)
        # Reference pixels outside the mask take their nearest mask pixel's value, so that
        # bilinear reads at the face boundary never mix in black.
        tri_index, _ = ref.rasterise()
        self.register_buffer("fill_index", torch.from_numpy(_nearest_inside(tri_index >= 0)))

    @property
    def n_candidates(self) -> int:
        return int(self.cand_tri.numel())

    def forward(self, textures: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, c = textures.shape[0], textures.shape[1]
        h, w = self.canvas
        ref_img = textures[:, :, self.fill_index].reshape(b, c, self.ref_size[0], self.ref_size[1])
        v = target[:, self.tri]  # (B, T, 3, 2)
        v0 = v[:, :, 0]
        e1 = v[:, :, 1] - v0
        e2 = v[:, :, 2] - v0
        det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]  # (B, T)
        lo = torch.floor(torch.amin(v, dim=2))  # (B, T, 2)
        px = lo[:, self.cand_tri] + self.cand_off  # (B, Nc, 2)
        d = px - v0[:, self.cand_tri]
        e1c, e2c, detc = e1[:, self.cand_tri], e2[:, self.cand_tri], det[:, self.cand_tri]
        safe = torch.where(detc.abs() > 1e-6, detc, torch.ones_like(detc))
        l1 = (d[..., 0] * e2c[..., 1] - d[..., 1] * e2c[..., 0]) / safe
        l2 = (e1c[..., 0] * d[..., 1] - e1c[..., 1] * d[..., 0]) / safe
        l0 = 1.0 - l1 - l2
        eps = 1e-5
        valid = (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps) & (detc > 1e-6)
        valid = valid & (px[..., 0] >= 0) & (px[..., 0] <= w - 1) & (px[..., 1] >= 0) & (px[..., 1] <= h - 1)
        bary = torch.stack([l0, l1, l2], -1)  # (B, Nc, 3)
        src = (bary.unsqueeze(-1) * self.cand_ref).sum(-2)  # (B, Nc, 2) reference coordinates
        flat = (px[..., 1] * w + px[..., 0]).to(torch.int64)
        flat = torch.where(valid, flat, torch.full_like(flat, h * w))
        buf = torch.full((b, h * w + 1, 2), _FAR, dtype=src.dtype, device=src.device)
        buf = buf.scatter(1, flat.unsqueeze(-1).expand(-1, -1, 2), src)
        grid = to_grid(buf[:, : h * w], self.ref_size).reshape(b, h, w, 2)
        img = F.grid_sample(ref_img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        mask = (buf[:, : h * w, :1] > _FAR / 2).to(img.dtype).reshape(b, 1, h, w)
        return img * mask, mask

    def clipped_triangles(self, target: torch.Tensor) -> torch.Tensor:
        """bool (B, T): triangles whose bounding box exceeds their candidate block (holes)."""
        v = target[:, self.tri]
        ext = torch.floor(torch.amax(v, 2)) - torch.floor(torch.amin(v, 2)) + 1
        return (ext > self.span).any(-1)


def candidate_spans(ref: ReferenceFrame, shapes: np.ndarray, safety: float = 1.3) -> np.ndarray:
    """Candidate block size of each triangle for :class:`ToTarget`.

    Parameters
    ----------
    ref : ReferenceFrame
    shapes : np.ndarray
        (N, 68, 2) example target shapes in canvas coordinates (e.g. the training shapes
        aligned to the reference frame, and their +-3 sigma extremes).
    safety : float
        Factor on the largest observed bounding box of each triangle.

    Returns
    -------
    np.ndarray
        int64 (T, 2): (width, height) in pixels.
    """
    pts = np.concatenate([np.asarray(shapes, np.float64).reshape(-1, len(ref.points), 2), ref.points[None]], 0)
    corners = pts[:, ref.triangles]  # (N, T, 3, 2)
    span = np.floor(corners.max(2) - corners.min(2)).max(0) + 2  # largest bbox + rounding
    return np.ceil(span * safety).astype(np.int64)


def _nearest_inside(mask: np.ndarray) -> np.ndarray:
    """For each pixel of a (H, W) mask, the index (into the mask's True pixels, in raster
    order) of the nearest True pixel: int64 (H*W,)."""
    from scipy import ndimage

    _, (iy, ix) = ndimage.distance_transform_edt(~mask, return_indices=True)
    order = np.full(mask.size, -1, np.int64)
    order[np.flatnonzero(mask.reshape(-1))] = np.arange(int(mask.sum()))
    return order[(iy * mask.shape[1] + ix).reshape(-1)]


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
