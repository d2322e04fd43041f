"""Piecewise-affine warps as batched tensor ops (exportable to ONNX: no Python loops
over pixels or triangles, no custom ops).

Two directions:

* :class:`ToReference` samples images into the reference frame (training textures).
  The reference geometry is fixed, so every reference pixel's triangle and barycentric
  coordinates are precomputed; a frame is one (M, 68) matmul and one ``grid_sample``.
* :class:`ToTarget` warps a reference-frame
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

One module for both directions of the one warp (the reference geometry, its triangles and the
pixel conventions they share); :class:`ToTarget`'s scan conversion, its per-frame tables and
its dense-mesh path are most of it, hence its length.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.model.reference import ReferenceFrame
from facesynth.model.restore import Restore
from facesynth.ops import pad_by_tensor, sum4


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


PER_PIXEL_TRIANGLES = 256  # above this many triangles, pixels gather their triangle's map (dense meshes)


class ToTarget(nn.Module):
    """Warp reference-frame textures onto target landmark sets (piecewise affine).

    The triangle covering each output pixel is found by *scanline coverage counting*
    along canvas columns (the edge-event form of polygon scan conversion; Foley et al.,
    "Computer Graphics: Principles and Practice", 2nd ed., sec. 3.6): each mesh edge
    crosses at most ``n_e`` canvas columns (the narrower ``span`` of its triangles); at each
    crossing it adds, at the first pixel below the crossing, ``+code`` for the triangle
    it starts (the triangle below it) and ``-code`` for the one it ends, and a cumulative
    sum down each column leaves, at every pixel, the sum of the codes of the triangles
    that cover it. ``code = C + t + 1`` with ``C`` a power of two above the triangle
    count, so one sum gives both the coverage count and the triangle index. A flipped
    triangle (orientation opposite to the reference: a fold) takes its codes with the
    opposite sign, so it too adds ``+code`` inside itself: the sum counts *unsigned*
    coverage and no fold leaves a hole. Every covered pixel is inside the face (the mask
    is the union of the target triangles, which contains the face outline whatever the
    folds); a pixel covered exactly once reads its triangle's affine map, and a pixel
    covered by two or more (where a fold overlaps the mesh) reads the reference texture at
    its own canvas position (the target is similarity-aligned to the reference frame, so
    this is the mean-shape texture there). Only degenerate (zero-area) triangles are
    skipped. Both
    triangles of a shared edge take their events from one evaluation of that edge, so
    neighbours partition each column exactly (a pixel centre on an edge belongs to the
    triangle below it; columns are half-open on the right).

    Each pixel then reads its triangle's affine map (target -> reference pixels) from
    per-frame tables indexed by (triangle, canvas column) -- ``u = u_c[t, x] + u_y[t] (y - y_0[t])``
    with ``(x_0, y_0)`` the triangle's first vertex, likewise ``v`` -- and the 2x2 texture neighbourhood of its source point (bilinear,
    as ``grid_sample`` with ``align_corners=True``) with flat element gathers.

    Only the bounding box of the landmarks (of the whole batch, clipped to the canvas) is
    evaluated: every triangle lies in it, so the pixels outside are outside the face; the
    result is zero-padded back to the canvas.

    Everything is a short, fixed list of tensor ops (GatherElements, MatMul,
    ScatterElements-add, CumSum, Range, Pad and elementwise ops): it exports to ONNX
    without loops or custom ops (the box makes the inner shapes data-dependent, which
    ONNX Runtime handles). Per image the cost is one event per (edge, column) it may cross
    and 5 + 12 gathered values per box pixel; the column sum runs along the outer axis of a
    (Hb + 1, Wb) buffer, which ONNX Runtime vectorises across the row (much faster than a
    sum along the rows; docs/runtime.md).

    Parameters
    ----------
    ref : ReferenceFrame
    span : np.ndarray
        int (T, 2): largest width and height (pixels) each triangle takes in the targets,
        from :func:`facesynth.model.warp.candidate_spans`; each edge visits as many columns as the narrower of
        its triangles (:meth:`clipped_triangles` reports targets that exceed the span).
    canvas : (H, W), optional
        Output size; defaults to the reference frame size.
    restore : (k, k) array, optional
        A restoration filter applied to the warped face (:class:`facesynth.model.restore.Restore`).
    offset : (C * M,) array, optional
        A constant added to every texture before the warp (clipped to [0, 1] after): the mean
        texture's restoration (:func:`facesynth.model.restore.apply_path`).

    Forward
    -------
    textures : (B, C, M) float tensor (M reference mask pixels, as from ToReference)
    target : (B, P, 2) float tensor, landmarks in canvas pixel coordinates
    returns : image (B, C, H, W) with zeros outside the face, mask (B, 1, H, W) in {0, 1}
    """

    def __init__(self, ref: ReferenceFrame, span: np.ndarray, canvas: tuple[int, int] | None = None,
                 restore: np.ndarray | None = None, offset: np.ndarray | None = None):
        super().__init__()
        self.restore = None if restore is None else Restore(restore)
        self.register_buffer("offset", None if offset is None else torch.from_numpy(np.asarray(offset, np.float32).reshape(1, -1)))
        self.canvas = tuple(int(s) for s in (canvas or ref.size))
        self.ref_size = tuple(int(s) for s in ref.size)
        tri = np.asarray(ref.triangles, np.int64)
        span = np.asarray(span, np.int64).reshape(-1, 2)
        self.n_tri = n_tri = len(tri)
        self.code_base = float(2 ** int(np.ceil(np.log2(n_tri + 2))))
        self.register_buffer("tri", torch.from_numpy(tri))
        self.register_buffer("span", torch.from_numpy(span.astype(np.float32)))
        edge_coords = self._init_edges(tri, span)
        self._init_affine(tri, edge_coords)
        c0, r0, rw = self._init_raster(ref, tri)
        self._init_pixels(c0, r0, rw)

    def _init_edges(self, tri: np.ndarray, span: np.ndarray) -> np.ndarray:
        """The edges' triangle codes and the scanline events (edge x column crossings); the
        flat landmark index of each edge's end points, (4 E,)."""
        n_tri, c, w = self.n_tri, self.code_base, self.canvas[1]
        # undirected edges (lo, hi) (vertex indices lo < hi); half-edge (t, k) runs from
        # tri[t, k] to tri[t, k + 1] and is +1 when it runs from lo to hi
        he_from, he_to = tri, tri[:, [1, 2, 0]]
        lo, hi = np.minimum(he_from, he_to), np.maximum(he_from, he_to)
        edges, he_edge = np.unique(np.stack([lo.reshape(-1), hi.reshape(-1)], 1), axis=0, return_inverse=True)
        he_edge = he_edge.reshape(-1)
        n_edge = len(edges)
        # a half-edge running towards +x starts its triangle below the crossing (+code),
        # towards -x it ends it: code matrix (T, E) of the lo -> hi direction
        code = c + 1.0 + np.arange(n_tri, dtype=np.float64)
        he_sign = np.where(he_from == lo, 1.0, -1.0).reshape(-1)
        # each edge has one or two triangles: its code is a sum of two gathered terms, valid[t] *
        # signed code, with boundary edges reading a constant 0 (index T); a dense (T, E) matmul
        # would cost T E per image (1.2 M for the 478-point mesh)
        edge_tri = np.full((2, n_edge), n_tri, np.int64)
        edge_code = np.zeros((2, n_edge))
        slot = np.zeros(n_edge, np.int64)
        for half, (t, ed) in enumerate(zip(np.repeat(np.arange(n_tri), 3), he_edge, strict=True)):
            edge_tri[slot[ed], ed], edge_code[slot[ed], ed] = t, he_sign[half] * code[t]
            slot[ed] += 1
        if slot.max() > 2:
            raise ValueError("triangulation has an edge shared by more than two triangles")
        self.register_buffer("edge_tri", torch.from_numpy(edge_tri.reshape(1, -1)))  # (1, 2 E) into [valid, 0]
        self.register_buffer("edge_code", torch.from_numpy(edge_code.astype(np.float32)))  # (2, E)
        edge_coords = np.stack([2 * edges[:, 0], 2 * edges[:, 0] + 1, 2 * edges[:, 1], 2 * edges[:, 1] + 1]).reshape(-1)
        # columns each edge may cross: an edge lies in the bounding box of each of its
        # triangles, so the narrower of their spans bounds it
        width = np.full(n_edge, w, np.int64)
        np.minimum.at(width, he_edge, np.repeat(np.maximum(span[:, 0], 1), 3))
        ev_edge = np.repeat(np.arange(n_edge), width)
        ev_k = np.arange(len(ev_edge)) - np.repeat(np.cumsum(width) - width, width)
        self.n_edges = n_edge
        self.n_scanline_events = int(len(ev_edge))  # the ONNX metadata key of the same name
        # per-event parameter gather: 5 per-edge fields [x0, columns, y at x0, slope, delta]
        ev_index = (np.arange(5)[:, None] * n_edge + ev_edge[None, :]).reshape(1, -1)
        self.register_buffer("ev_index", torch.from_numpy(ev_index))
        self.register_buffer("ev_k", torch.from_numpy(ev_k.astype(np.float32)))
        return edge_coords

    def _init_affine(self, tri: np.ndarray, edge_coords: np.ndarray) -> None:
        """The landmark gather and the linear maps of the per-triangle affine maps."""
        n_tri = self.n_tri
        # affine maps: vertices [x0 y0 x1 y1 x2 y2] -> edge vectors etc. (linear maps)
        vert = np.stack([2 * tri, 2 * tri + 1], -1).reshape(n_tri, 6)
        # one element gather of the flat landmarks: triangle vertices field-major (6 T), then edge end
        # points (4 E) (row Gathers are far slower per index in ONNX Runtime; docs/runtime.md). Per-triangle
        # values are (B, fields, T), so elementwise ops run along T (docs/runtime.md, "Batch-1 tuning")
        self.register_buffer("coord_index", torch.from_numpy(np.concatenate([vert.T.reshape(-1), edge_coords])[None]))
        p_edges = np.zeros((4, 6), np.float32)  # [x0 y0 x1 y1 x2 y2] -> e1x e1y e2x e2y
        for j, (a, b) in enumerate([(2, 0), (3, 1), (4, 0), (5, 1)]):
            p_edges[j, a], p_edges[j, b] = 1, -1
        p_swap = np.zeros((2, 4), np.float32)  # -> e2y e2x (for det = e1x e2y - e1y e2x)
        p_swap[0, 3] = p_swap[1, 2] = 1
        p_ab = np.zeros((4, 4), np.float32)  # -> det * [a1, b1, a2, b2] = [e2y, -e2x, -e1y, e1x]
        p_ab[0, 3], p_ab[1, 2], p_ab[2, 1], p_ab[3, 0] = 1, -1, -1, 1
        self.register_buffer("p_edges", torch.from_numpy(p_edges))
        self.register_buffer("p_swap", torch.from_numpy(p_swap))
        self.register_buffer("p_det", torch.tensor([[1.0, -1.0]]))
        self.register_buffer("p_ab", torch.from_numpy(p_ab))

    def _init_raster(self, ref: ReferenceFrame, tri: np.ndarray) -> tuple[int, int, int]:
        """The texture raster and the reference triangles in its coordinates; (c0, r0, raster width)."""
        # the texture raster: the reference mask's bounding box plus 2 px, reference pixels
        # outside the mask filled with their nearest mask pixel's value, so that bilinear
        # reads at the face boundary never mix in black
        hr, wr = self.ref_size
        tri_index, _ = ref.rasterise()
        inside_ref = tri_index >= 0
        fill = _nearest_inside(inside_ref)
        self.register_buffer("fill_index", torch.from_numpy(fill))  # (Hr * Wr,) into the M mask pixels
        self.n_mask = int(inside_ref.sum())
        ys_in, xs_in = np.nonzero(inside_ref)
        r0, r1 = max(int(ys_in.min()) - 2, 0), min(int(ys_in.max()) + 3, hr)
        c0, c1 = max(int(xs_in.min()) - 2, 0), min(int(xs_in.max()) + 3, wr)
        self.raster_box = (r0, r1, c0, c1)
        rh, rw = r1 - r0, c1 - c0
        self.raster_w = rw
        self.n_raster = rh * rw
        self.register_buffer("raster_fill", torch.from_numpy(fill.reshape(hr, wr)[r0:r1, c0:c1].reshape(-1).copy()))
        # u = ref_0x + l1 (ref_1 - ref_0)_x + l2 (ref_2 - ref_0)_x (likewise v), with barycentric
        # l_i = a_i (x - x_0) + b_i (y - y_0) taken relative to the target triangle's vertex 0, so
        # that no large canvas coordinates cancel (float32 parity between torch and ONNX Runtime);
        # in raster coordinates (reference pixels minus the box origin)
        rp = ref.points[tri].astype(np.float64) - np.array([c0, r0], np.float64)  # (T, 3, 2)
        rp = rp.transpose(1, 2, 0)[:, :, None]  # (3, 2, 1, T): [[x], [y]] per vertex, float64
        for name, d in (("ref_d1", rp[1] - rp[0]), ("ref_d2", rp[2] - rp[0]), ("ref_0", rp[0])):  # (2, 1, T)
            self.register_buffer(name, torch.from_numpy(np.ascontiguousarray(d, np.float32)))
        # overlap pixels (covered twice or more, by a fold) read the raster at their own canvas
        # position: u = x - c0, v = y - r0 (table column T + 1, origin (0, 0)); (6, 1)
        self.register_buffer("overlap_map", torch.tensor([[1.0], [0.0], [-float(c0)], [0.0], [1.0], [-float(r0)]]))
        return c0, r0, rw

    def _init_pixels(self, c0: int, r0: int, rw: int) -> None:
        """Per-pixel constants of the canvas."""
        (h, w), c = self.canvas, self.code_base
        # per-pixel constants: column x, row y, table offset x - C W (tables are (T + 2, W))
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
        self.register_buffer("col_x", torch.arange(w, dtype=torch.float32))
        self.register_buffer("pix_y", torch.from_numpy(ys.reshape(1, -1)))
        self.register_buffer("table_off", torch.from_numpy((xs - c * w).astype(np.float32)))  # (H, W)
        self.register_buffer("quad_offset", torch.tensor([0, 1, rw, rw + 1]).reshape(4, 1, 1))
        self.base_max = float(self.n_raster - rw - 2)
        self.register_buffer("ones4", torch.ones(1, 4))
        self.register_buffer("canvas_max", torch.tensor([float(w), float(h)]))  # (x, y) limits
        self.register_buffer("zero2", torch.zeros(2))

    def _fill_tables(self, c: int) -> list[torch.Tensor]:
        """Raster fill index of each of ``c`` channels into (C * M): (1, n_raster) each,
        constants of an exported graph (built from ``int(c)``, no Shape -> Range chain)."""
        return [self.raster_fill.reshape(1, -1) + ch * self.n_mask for ch in range(int(c))]

    # ---------------------------------------------------------------- pieces
    def coordinates(self, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Target vertices (B, 6, T) [x0 y0 x1 y1 x2 y2], their edge vectors (B, 4, T)
        [e1x e1y e2x e2y] and the edge end points (B, 4, E) [x_lo, y_lo, x_hi, y_hi]."""
        flat = target.flatten(1)
        index = torch.zeros_like(flat[:, :1], dtype=torch.int64) + self.coord_index
        coords = torch.gather(flat, 1, index)
        vert = coords[:, : 6 * self.n_tri].reshape(-1, 6, self.n_tri)
        return vert, torch.matmul(self.p_edges, vert), coords[:, 6 * self.n_tri:].reshape(-1, 4, self.n_edges)

    def box(self, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The canvas pixels that any triangle can cover: float (2,) tensors lo = [x_lo, y_lo]
        and hi = [x_hi, y_hi] (pixel centres lo <= (x, y) < hi), the bounding box of all the
        landmarks of the batch clipped to the canvas (at least one pixel). Every triangle lies
        in it, so pixels outside are outside the face and need not be evaluated."""
        xy = target.reshape(-1, 2)
        lo, hi = torch.ceil(xy.amin(0)), torch.floor(xy.amax(0)) + 1.0
        # a NaN landmark (a frame without a face) makes the box the whole canvas; its own
        # triangles are then all degenerate and it renders empty, as without the box
        lo = torch.where(torch.isnan(lo), torch.zeros_like(lo), lo)
        hi = torch.where(torch.isnan(hi), self.canvas_max, hi)
        lo = torch.minimum(torch.clamp(lo, min=0.0), self.canvas_max - 1.0)
        hi = torch.minimum(torch.maximum(hi, lo + 1.0), self.canvas_max)
        return lo, hi

    def locate(self, ed: torch.Tensor, det: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
               cols: torch.Tensor, rows_ext: torch.Tensor) -> torch.Tensor:
        """Coverage code sum of every box pixel, float (B, Hb, Wb): 0 outside, ``C + t + 1``
        inside triangle t, more where triangles overlap.

        ed : (B, 4, E) edge end points and det : (B, 1, T) determinants, from
        :meth:`coordinates` / :meth:`affine_maps`; lo, hi : the box from :meth:`box`;
        cols (Wb,) and rows_ext (Hb + 1,): its pixel columns and rows plus one row below.
        """
        x_lo, y_lo, x_hi = lo[0], lo[1], hi[0]
        wb, hb = x_hi - x_lo, hi[1] - y_lo
        xa, ya, xb, yb = ed[:, 0:1], ed[:, 1:2], ed[:, 2:3], ed[:, 3:4]  # (B, 1, E)
        # +1 for reference-oriented triangles, -1 for flipped ones (their edge events are
        # reversed, so the product adds +code inside either); degenerate ones are skipped
        valid = (det > 1e-6).to(ed.dtype) - (det < -1e-6).to(ed.dtype)  # (B, 1, T)
        valid = torch.cat([valid.flatten(1), valid[:, 0, :1] * 0.0], 1)  # (B, T + 1): index T reads 0
        index = torch.zeros_like(valid[:, :1], dtype=torch.int64) + self.edge_tri
        terms = torch.gather(valid, 1, index).reshape(-1, 2, self.n_edges) * self.edge_code
        codes = (terms[:, 0] + terms[:, 1]).unsqueeze(1)  # (B, 1, E): signed codes, lo -> hi direction
        dx = xb - xa
        delta = torch.where(dx > 0, codes, -codes)
        slope = (yb - ya) / torch.where(dx == 0, 1.0, dx)
        x0 = torch.maximum(torch.ceil(torch.minimum(xa, xb)), x_lo)
        n_cols = torch.minimum(torch.maximum(xa, xb), x_hi) - x0  # columns x0 + k, k < n_cols
        y0 = (x0 - xa) * slope + ya - y_lo  # box rows
        fields = torch.cat([x0 - x_lo, n_cols, y0, slope, delta], 1).flatten(1)  # (B, 5 E)
        index = torch.zeros_like(fields[:, :1], dtype=torch.int64) + self.ev_index
        ev = torch.gather(fields, 1, index).reshape(-1, 5, self.n_scanline_events)
        k = self.ev_k
        row = torch.clamp(torch.ceil(ev[:, 2] + k * ev[:, 3]), min=0.0)
        row = torch.minimum(row, hb)
        # events past the edge's end, or below the box, land in row Hb (dropped)
        idx = torch.where(k < ev[:, 1], row * wb + (ev[:, 0] + k), hb * wb).to(torch.int64)
        grid = rows_ext.unsqueeze(1) * 0.0 + cols * 0.0  # (Hb + 1, Wb) zeros
        buf = torch.zeros_like(fields[:, :1]) + grid.reshape(1, -1)  # (B, (Hb + 1) Wb)
        s = buf.scatter_add(1, idx, ev[:, 4]).reshape(-1, rows_ext.shape[0], cols.shape[0])
        return torch.cumsum(s, 1)[:, :-1]

    def affine_maps(self, vert: torch.Tensor, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-triangle affine maps, target canvas pixels -> raster pixels (reference pixels
        minus the raster box origin), relative to each target triangle's vertex 0, and the
        triangles' determinants.

        vert, e : from :meth:`coordinates`. Returns maps (B, 6, T): per triangle
        [u_x, u_y, u_0, v_x, v_y, v_0] with u = u_0 + u_x (x - x_0) + u_y (y - y_0)
        ((x_0, y_0) = ``vert[:, :2]``; barycentric interpolation), and det (B, 1, T)
        (> 0 for counter-clockwise target triangles).
        """
        det = torch.matmul(self.p_det, e[:, :2] * torch.matmul(self.p_swap, e))  # (B, 1, T)
        inv = 1.0 / torch.where(det.abs() > 1e-12, det, 1.0)
        ab = torch.matmul(self.p_ab, e) * inv  # (B, 4, T): [a1, b1, a2, b2]
        grad = ab[:, 0:2].unsqueeze(1) * self.ref_d1 + ab[:, 2:4].unsqueeze(1) * self.ref_d2  # (B, 2, 2, T): [[u_x u_y], [v_x v_y]]
        maps = torch.cat([grad, self.ref_0 + grad[:, :, :1] * 0.0], 2)  # (B, 2, 3, T)
        return maps.reshape(-1, 6, self.n_tri), det

    def source(self, maps: torch.Tensor, origin: torch.Tensor, s: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
               cols: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raster coordinates u, v (B, 1, Hb, Wb) of every box pixel given its code sum.

        maps : (B, 6, T) from :meth:`affine_maps`; origin : (B, 2, T) the triangles' vertex 0
        (x_0, y_0); s : (B, 1, Hb, Wb) from :meth:`locate`; lo, hi : the box; cols (Wb,),
        rows (Hb,): its canvas coordinates. Tables (B, (T + 2) Wb) indexed by
        ``(s' - C) Wb + (x - x_lo)`` with s' = clamp(s, C, C + T + 1) hold
        u_c = u_0 + u_x (x - x_0), u_y and y_0 (likewise v); u = u_c + u_y (y - y_0). Row 0
        (no triangle) maps to (0, 0) and row T + 1 (two or more triangles: a fold's
        overlap) to the pixel's own canvas position in the raster. Every product is
        of a small offset (a pixel's distance to its triangle's vertex), so float32 rounding
        stays at the level of the raster coordinates (<= 1e-5 px on a 400 px canvas).
        """
        tab = torch.cat([F.pad(maps, (1, 0)), self.overlap_map + maps[:, :, :1] * 0.0], 2)  # (B, 6, T + 2), column t + 1 = triangle t
        org = F.pad(origin, (1, 1))  # (B, 2, T + 2)
        if self.n_tri > PER_PIXEL_TRIANGLES:
            return self._source_per_pixel(tab, org, s, cols, rows)
        zero = cols * 0.0
        tab, org = tab.unsqueeze(-1), org.unsqueeze(-1)  # (B, 6 | 2, T + 2, 1)
        dx = cols - org[:, 0]  # (B, T + 2, Wb)
        u0 = (tab[:, 0] * dx + tab[:, 2]).flatten(1)  # (B, (T + 2) Wb)
        uy = (tab[:, 1] + zero).flatten(1)
        v0 = (tab[:, 3] * dx + tab[:, 5]).flatten(1)
        vy = (tab[:, 4] + zero).flatten(1)
        y0 = (org[:, 1] + zero).flatten(1)
        wb = hi[0] - lo[0]
        offset = cols - (lo[0] + self.code_base * wb)  # (Wb,)
        index = (torch.clamp(s, self.code_base, self.code_base + self.n_tri + 1) * wb + offset).to(torch.int64).flatten(1)
        dy = rows.unsqueeze(1) - torch.gather(y0, 1, index).reshape_as(s)  # (B, 1, Hb, Wb)
        u = torch.gather(u0, 1, index).reshape_as(s) + torch.gather(uy, 1, index).reshape_as(s) * dy
        v = torch.gather(v0, 1, index).reshape_as(s) + torch.gather(vy, 1, index).reshape_as(s) * dy
        return u, v

    def _source_per_pixel(self, tab: torch.Tensor, org: torch.Tensor, s: torch.Tensor, cols: torch.Tensor,
                          rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`source` for dense meshes: each pixel gathers its triangle's (x_0, y_0, u_x, u_y,
        u_0, v_x, v_y, v_0) instead of reading (T + 2) Wb-entry tables; same products, same order.
        One gather per field, all with the pixel's triangle as index (one (B, 8 N) gather would
        need an 8 N-element index sum every frame)."""
        t = (torch.clamp(s, self.code_base, self.code_base + self.n_tri + 1) - self.code_base).to(torch.int64).flatten(1)
        x0, y0, ux, uy, u0, vx, vy, v0 = (torch.gather(table[:, k], 1, t).reshape_as(s)
                                          for table, k in [(org, 0), (org, 1)] + [(tab, k) for k in range(6)])
        dx = cols - x0
        dy = rows.unsqueeze(1) - y0
        u = ux * dx + u0 + uy * dy
        v = vx * dx + v0 + vy * dy
        return u, v

    def bilinear(self, textures: torch.Tensor, u: torch.Tensor, v: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
        """Bilinear reads of reference textures, zero where ``inside`` is 0.

        textures : (B, C, M) mask-pixel textures; u, v : (B, 1, Hb, Wb) raster coordinates;
        inside : (B, 1, Hb, Wb) float. Returns (B, C, Hb, Wb).
        """
        c = int(textures.shape[1])
        flat = textures.flatten(1)
        zero = torch.zeros_like(flat[:, :1], dtype=torch.int64)
        fu, fv = torch.floor(u), torch.floor(v)
        fx, fy = u - fu, v - fv
        base = torch.clamp(fv * float(self.raster_w) + fu, 0.0, self.base_max).to(torch.int64)  # (B, 1, Hb, Wb)
        index = (base + self.quad_offset).flatten(1)  # (B, 4 N): the 2x2 neighbours
        wy = torch.cat([1.0 - fy, fy], 1) * inside  # (B, 2, Hb, Wb)
        wx = torch.cat([1.0 - fx, fx], 1)
        weights = (wy.unsqueeze(2) * wx.unsqueeze(1)).flatten(1, 2).flatten(2)  # (B, 4, N): top-left, top-right, bottom-left, bottom-right
        out = []
        for table in self._fill_tables(c):  # one raster per channel, all read with the same index
            raster = torch.gather(flat, 1, zero + table)  # (B, R)
            taps = torch.gather(raster, 1, index).reshape_as(weights)
            out.append(sum4(self.ones4, taps * weights).reshape_as(inside))
        return out[0] if c == 1 else torch.cat(out, 1)

    def forward(self, textures: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.offset is not None:
            textures = torch.clamp(textures + self.offset.reshape(1, textures.shape[1], -1), 0.0, 1.0)
        vert, e, ed = self.coordinates(target)
        maps, det = self.affine_maps(vert, e)
        lo, hi = self.box(target)
        cols, rows = torch.arange(lo[0], hi[0]), torch.arange(lo[1], hi[1] + 1.0)  # box pixels, one row more
        s = self.locate(ed, det, lo, hi, cols, rows).unsqueeze(1)  # (B, 1, Hb, Wb)
        cb = self.code_base
        inside = (s > cb * 0.5).to(textures.dtype)  # covered at least once (codes are >= C + 1)
        u, v = self.source(maps, vert[:, :2], s, lo, hi, cols, rows[:-1])
        img = self.bilinear(textures, u, v, inside)
        # ONNX Pad order: begins of (B, C, H, W), then ends
        pads = torch.cat([self.zero2, lo.flip(0), self.zero2, (self.canvas_max - hi).flip(0)]).to(torch.int64)
        img, inside = pad_by_tensor(img, pads), pad_by_tensor(inside, pads)
        if self.restore is not None:
            img = self.restore(img, inside)
        return img, inside

    def clipped_triangles(self, target: torch.Tensor) -> torch.Tensor:
        """bool (B, T): triangles wider than their ``span`` (their edges may miss columns)."""
        v = target[:, self.tri]
        ext = torch.floor(torch.amax(v, 2)) - torch.floor(torch.amin(v, 2)) + 1
        return ext[..., 0] > self.span[:, 0]


def _nearest_inside(mask: np.ndarray) -> np.ndarray:
    """For each pixel of a (H, W) mask, the index (into the mask's True pixels, in raster
    order) of the nearest True pixel: int64 (H*W,)."""
    from scipy import ndimage

    _, (iy, ix) = ndimage.distance_transform_edt(~mask, return_indices=True)
    order = np.full(mask.size, -1, np.int64)
    order[np.flatnonzero(mask.reshape(-1))] = np.arange(int(mask.sum()))
    return order[(iy * mask.shape[1] + ix).reshape(-1)]
