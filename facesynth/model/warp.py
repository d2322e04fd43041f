"""Piecewise-affine warps as batched tensor ops (exportable to ONNX: no Python loops
over pixels or triangles, no custom ops).

Two directions:

* :class:`ToReference` samples images into the reference frame (training textures).
  The reference geometry is fixed, so every reference pixel's triangle and barycentric
  coordinates are precomputed; a frame is one (M, 68) matmul and one ``grid_sample``.
* :class:`ToTarget` warps a reference-frame texture onto any target landmark set
  (rendering). The triangle covering each output pixel is found by *scanline coverage
  counting*: each triangle edge adds a signed triangle code at its row crossings
  (scatter-add over at most ``span`` rows, sized from the training shapes by
  :func:`candidate_spans`), and a cumulative sum along each row yields the covering
  triangle; each pixel then gathers its triangle's affine map and bilinear taps. Its
  cost is a few gathers per canvas pixel, instead of (pixels x triangles) tests.

Coordinates: (x, y), integer values at pixel centres; ``grid_sample`` uses
``align_corners=True`` so that this matches OpenCV's ``remap``/``warpAffine``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.model.reference import ReferenceFrame



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
    """Warp reference-frame textures onto target landmark sets (piecewise affine).

    The triangle covering each output pixel is found by *scanline coverage counting*
    (the edge-event form of polygon scan conversion; Foley et al., "Computer Graphics:
    Principles and Practice", 2nd ed., sec. 3.6): each triangle edge crosses at most
    ``span[:, 1].max()`` canvas rows; at each crossing it adds ``+code`` (left edge of its
    triangle) or ``-code`` (right edge) at the first pixel right of the crossing, and a
    cumulative sum along each row leaves, at every pixel, the sum of the codes of the
    triangles that cover it. ``code = C + t + 1`` with ``C`` a power of two above the
    triangle count, so one sum gives both the coverage count and the triangle index;
    pixels covered exactly once are inside (degenerate or flipped triangles are skipped).
    Shared edges are evaluated from the same two vertices in the same order for both
    triangles, so neighbours partition each row exactly (a pixel centre on an edge
    belongs to the triangle on its right; rows are half-open at the bottom). Each pixel
    then reads its triangle's affine map (target -> reference pixels) and the 2x2
    texture neighbourhood of its source point (bilinear, as ``grid_sample`` with
    ``align_corners=True``) with flat element gathers.

    Everything is a short, fixed list of tensor ops (Gather, MatMul, ScatterElements-add,
    CumSum, GatherElements and elementwise ops, about 80 ONNX nodes): it exports to ONNX
    without loops or custom ops; the cost is (3 T x span rows) edge events plus 18
    gathered values per canvas pixel.

    Parameters
    ----------
    ref : ReferenceFrame
    span : np.ndarray
        int (T, 2): largest width and height (pixels) each triangle takes in the targets,
        from :func:`candidate_spans`; each edge visits ``span[:, 1].max()`` rows
        (:meth:`clipped_triangles` reports targets that exceed the span).
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
        self.canvas = tuple(int(s) for s in (canvas or ref.size))
        self.ref_size = tuple(int(s) for s in ref.size)
        tri = np.asarray(ref.triangles, np.int64)
        span = np.asarray(span, np.int64)
        n_tri = len(tri)
        h, w = self.canvas
        hr, wr = self.ref_size
        n_ref = hr * wr
        self.n_tri = n_tri
        self.code_base = float(2 ** int(np.ceil(np.log2(n_tri + 2))))
        self.n_rows = max(int(span[:, 1].max()) if len(span) else 1, 1)
        self.register_buffer("tri", torch.from_numpy(tri))
        self.register_buffer("span", torch.from_numpy(span.astype(np.float32)))
        # half-edges (t, k) go from tri[t, k] to tri[t, k + 1]; both half-edges of an edge
        # are evaluated from its lower-index vertex ("lo") to its higher-index one ("hi")
        he_from, he_to = tri, tri[:, [1, 2, 0]]
        lo, hi = np.minimum(he_from, he_to), np.maximum(he_from, he_to)
        fields = np.stack([2 * lo, 2 * lo + 1, 2 * hi, 2 * hi + 1])  # (4, T, 3) into (68 * 2,)
        self.register_buffer("edge_index", torch.from_numpy(fields.reshape(-1)))
        # +code where the half-edge runs upwards (lo above hi and from == hi, ...): the
        # triangle (counter-clockwise, det > 0) then lies right of the crossing
        code = self.code_base + 1.0 + np.arange(n_tri, dtype=np.float64)[:, None]
        signed = np.where(he_from == lo, 1.0, -1.0) * code  # sign when y_lo > y_hi
        self.register_buffer("edge_code", torch.from_numpy(signed.astype(np.float32)[..., None]))  # (T, 3, 1)
        self.register_buffer("rows", torch.arange(self.n_rows, dtype=torch.float32))
        vert = np.stack([2 * tri, 2 * tri + 1], -1).reshape(n_tri, 6)  # x0 y0 x1 y1 x2 y2
        self.register_buffer("vert_index", torch.from_numpy(vert.reshape(-1)))
        # linear maps on [x0, y0, x1, y1, x2, y2]: edge vectors, their swaps, v0
        p_edges = np.zeros((6, 4), np.float32)  # -> e1x e1y e2x e2y
        for j, (a, b) in enumerate([(2, 0), (3, 1), (4, 0), (5, 1)]):
            p_edges[a, j], p_edges[b, j] = 1, -1
        p_swap = np.zeros((4, 4), np.float32)  # -> e2y e2x (for det = e1x e2y - e1y e2x)
        p_swap[3, 0] = p_swap[2, 1] = 1
        p_ab = np.zeros((4, 4), np.float32)  # -> det * [a1, b1, a2, b2] = [e2y, -e2x, -e1y, e1x]
        p_ab[3, 0], p_ab[2, 1], p_ab[1, 2], p_ab[0, 3] = 1, -1, -1, 1
        p_v0 = np.zeros((6, 4), np.float32)  # -> v0x v0y v0x v0y
        p_v0[0, 0] = p_v0[1, 1] = p_v0[0, 2] = p_v0[1, 3] = 1
        p_c = np.array([[-1, 0], [-1, 0], [0, -1], [0, -1]], np.float32)  # -> c1, c2
        self.register_buffer("p_edges", torch.from_numpy(p_edges))
        self.register_buffer("p_swap", torch.from_numpy(p_swap[:, :2]))
        self.register_buffer("p_det", torch.tensor([[1.0], [-1.0]]))
        self.register_buffer("p_ab", torch.from_numpy(p_ab))
        self.register_buffer("p_v0", torch.from_numpy(p_v0))
        self.register_buffer("p_c", torch.from_numpy(p_c))
        # [a1 b1 a2 b2 c1 c2] -> [u_x u_y u_1 v_x v_y v_1] per triangle: l1 (ref_1 - ref_0) + l2 (ref_2 - ref_0) + ref_0
        rp = ref.points[tri].astype(np.float64)  # (T, 3, 2)
        d1, d2 = rp[:, 1] - rp[:, 0], rp[:, 2] - rp[:, 0]
        m = np.zeros((n_tri, 6, 6))
        for q in range(2):  # u, v
            for col, (i1, i2) in enumerate([(0, 2), (1, 3), (4, 5)]):  # x, y, const coefficients of l1 / l2
                m[:, i1, 3 * q + col] = d1[:, q]
                m[:, i2, 3 * q + col] = d2[:, q]
        const = np.zeros((n_tri, 1, 6))
        const[:, 0, 2], const[:, 0, 5] = rp[:, 0, 0], rp[:, 0, 1]
        self.register_buffer("p_maps", torch.from_numpy(m.astype(np.float32)))  # (T, 6, 6)
        self.register_buffer("maps_const", torch.from_numpy(const.astype(np.float32)))  # (T, 1, 6)
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
        ones = np.ones(h * w, np.float32)
        xy1 = np.stack([xs.reshape(-1), ys.reshape(-1), ones, xs.reshape(-1), ys.reshape(-1), ones])
        self.register_buffer("xy1", torch.from_numpy(xy1.reshape(2, 3, h * w)))
        self.register_buffer("six", torch.arange(6).reshape(6, 1))
        self.register_buffer("zeros_row", torch.zeros(h * (w + 1) + 1))
        self.register_buffer("fl_max", torch.tensor([[wr - 2.0], [hr - 2.0]]))
        self.register_buffer("fl_flat", torch.tensor([[1.0, float(wr)]]))
        # Reference pixels outside the mask take their nearest mask pixel's value, so that
        # bilinear reads at the face boundary never mix in black.
        tri_index, _ = ref.rasterise()
        fill = _nearest_inside(tri_index >= 0)
        self.register_buffer("fill_index", torch.from_numpy(fill))
        self.n_mask = int((tri_index >= 0).sum())
        self.register_buffer("quad_offset", torch.tensor([0, 1, wr, wr + 1]))
        self.n_edge_events = 3 * n_tri * self.n_rows

    @property
    def n_candidates(self) -> int:
        """Number of scanline events evaluated per image (3 T edges x rows)."""
        return self.n_edge_events

    def _channel_tables(self, c: int) -> tuple[torch.Tensor, torch.Tensor]:
        """fill index into (C * M) and neighbour offsets into (C * H_ref * W_ref), per channel.

        Built from ``int(c)`` so that they are constants in an exported graph (no
        Shape -> Range chain evaluated per call)."""
        c = int(c)
        n_ref = self.ref_size[0] * self.ref_size[1]
        ch = np.arange(c, dtype=np.int64)
        fill_np = self.fill_index.cpu().numpy()
        fill = (fill_np[None, :] + ch[:, None] * self.n_mask).reshape(-1)
        quad = (self.quad_offset.cpu().numpy()[None, :] + ch[:, None] * n_ref).reshape(-1, 1)  # (4C, 1)
        dev = self.fill_index.device
        return torch.from_numpy(fill).to(dev), torch.from_numpy(quad).to(dev)

    # ---------------------------------------------------------------- pieces
    def locate(self, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Which triangle covers each canvas pixel.

        target : (B, 68, 2) canvas landmarks. Returns the triangle index as float (B, 1, H*W)
        (0 where not inside), inside as bool (B, 1, H*W) (covered by exactly one triangle),
        and the per-triangle vertices (B, T, 6) [x0 y0 x1 y1 x2 y2].
        """
        h, w = self.canvas
        n_tri = self.n_tri
        flat = target.flatten(1)  # batch sizes stay symbolic: reshapes use -1, no Shape ops
        vert = flat[:, self.vert_index].reshape(-1, n_tri, 6)
        e = torch.matmul(vert, self.p_edges)  # (B, T, 4)
        det = torch.matmul(e[..., :2] * torch.matmul(e, self.p_swap), self.p_det)  # (B, T, 1)
        ed = flat[:, self.edge_index].reshape(-1, 4, n_tri, 3, 1)
        xa, ya, xb, yb = ed[:, 0], ed[:, 1], ed[:, 2], ed[:, 3]  # (B, T, 3, 1)
        delta = torch.where(ya > yb, self.edge_code, -self.edge_code)
        delta = torch.where(det.unsqueeze(-1) > 1e-6, delta, 0.0)
        dy = yb - ya
        slope = (xb - xa) / torch.where(dy == 0, 1.0, dy)
        y0 = torch.clamp(torch.ceil(torch.minimum(ya, yb)), min=0.0)
        y1 = torch.clamp(torch.maximum(ya, yb), max=float(h))
        y = y0 + self.rows  # (B, T, 3, R)
        valid = y < y1
        col = torch.clamp(torch.ceil((y - ya) * slope + xa), 0.0, float(w))
        size = h * (w + 1)
        idx = torch.where(valid, y * float(w + 1) + col, float(size)).to(torch.int64).flatten(1)
        upd = torch.where(valid, delta, 0.0).flatten(1)
        buf = torch.zeros_like(upd[:, :1]) + self.zeros_row  # (B, size + 1); the last slot is a dump
        s = torch.cumsum(buf.scatter_add(1, idx, upd)[:, :size].reshape(-1, h, w + 1), 2)
        s = s[:, :, :w].reshape(-1, 1, h * w)
        c = self.code_base
        inside = (s > c + 0.5) & (s < 2 * c - 0.5)
        tri_id = torch.clamp(s - (c + 1.0), 0.0, float(n_tri - 1))
        return tri_id, inside, vert

    def affine_maps(self, vert: torch.Tensor) -> torch.Tensor:
        """Per-triangle affine maps, target canvas pixels -> reference pixels.

        vert : (B, T, 6) target vertices. Returns (B, T * 6): per triangle
        [u_x, u_y, u_1, v_x, v_y, v_1] with u = u_x x + u_y y + u_1 (barycentric interpolation).
        """
        e = torch.matmul(vert, self.p_edges)
        det = torch.matmul(e[..., :2] * torch.matmul(e, self.p_swap), self.p_det)
        inv = 1.0 / torch.where(det.abs() > 1e-12, det, 1.0)
        ab = torch.matmul(e, self.p_ab) * inv  # (B, T, 4) a1 b1 a2 b2
        cc = torch.matmul(ab * torch.matmul(vert, self.p_v0), self.p_c)  # (B, T, 2) c1 c2
        lin = torch.cat([ab, cc], -1).unsqueeze(-2)  # (B, T, 1, 6)
        return (torch.matmul(lin, self.p_maps) + self.maps_const).flatten(1)

    def source(self, maps: torch.Tensor, tri_id: torch.Tensor) -> torch.Tensor:
        """Reference coordinates (B, 2, H*W) [u; v] of every canvas pixel given its triangle.

        maps : (B, T * 6) from :meth:`affine_maps`; tri_id : (B, 1, H*W) float.
        """
        n = self.canvas[0] * self.canvas[1]  # constants, not Shape ops, in an exported graph
        index = (tri_id.to(torch.int64) * 6 + self.six).flatten(1)  # (B, 6 N)
        return (torch.gather(maps, 1, index).reshape(-1, 2, 3, n) * self.xy1).sum(2)

    def bilinear(self, textures: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear reads of reference textures.

        textures : (B, C, M) mask-pixel textures; uv : (B, 2, N) reference pixel coordinates.
        Returns (B, C, N).
        """
        c = int(textures.shape[1])
        n = self.canvas[0] * self.canvas[1]
        fill, quad = self._channel_tables(c)
        flat = textures.flatten(1)
        fill = torch.zeros_like(flat[:, :1], dtype=torch.int64) + fill  # (B, C * Hr * Wr)
        raster = torch.gather(flat, 1, fill)
        fl = torch.minimum(torch.clamp(torch.floor(uv), min=0.0), self.fl_max)
        frac = uv - fl  # (B, 2, N)
        base = torch.matmul(self.fl_flat, fl).to(torch.int64)  # (B, 1, N) y0 * W_ref + x0, exact
        index = (base + quad).flatten(1)  # (B, 4C N), channel-major then neighbour
        g = torch.gather(raster, 1, index).reshape(-1, c, 2, 2, n)  # (B, C, row, column, N)
        fx, fy = frac[:, :1].unsqueeze(2), frac[:, 1:]  # (B, 1, 1, N), (B, 1, N)
        left = g[:, :, :, 0]
        rows = left + fx * (g[:, :, :, 1] - left)  # (B, C, 2, N): top and bottom rows
        top = rows[:, :, 0]
        return top + fy * (rows[:, :, 1] - top)

    def forward(self, textures: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = int(textures.shape[1])
        h, w = self.canvas
        tri_id, inside, vert = self.locate(target)
        img = self.bilinear(textures, self.source(self.affine_maps(vert), tri_id))
        mask = inside.to(img.dtype)
        return (img * mask).reshape(-1, c, h, w), mask.reshape(-1, 1, h, w)

    def clipped_triangles(self, target: torch.Tensor) -> torch.Tensor:
        """bool (B, T): triangles wider or taller than their ``span`` (may leave holes)."""
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
