"""Geometry images: a mesh's x, y, z resampled over its UV layout (Gu et al. 2002).

A mesh with fixed topology and UVs is rasterised once into a per-pixel triangle index
and barycentric weights (:class:`UVLayout`); each frame is then a gather (a weighted sum
of three vertex positions per pixel), so a sequence of meshes becomes a geometry video
at hundreds of frames/s. Vertices are recovered by bilinear sampling at their UVs.

Conventions: UVs follow OBJ (v up), so pixel row ``i`` covers ``v = 1 - (i + 0.5) / H``
and column ``j`` covers ``u = (j + 0.5) / W``. Images are float64 (H, W, 3) in mesh
units, or uint16 after :func:`quantise`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from facesynth.errors import FacesynthError

PEAK16 = 65535


@dataclass(frozen=True)
class UVLayout:
    """Per-pixel triangle and barycentrics of a UV layout, computed once.

    Attributes
    ----------
    height, width : int
    faces : (F, 3) int64 vertex indices.
    pix : (P,) int64 flat pixel indices (row-major) that carry geometry.
    tri : (P,) int64 triangle of each such pixel.
    bary : (P, 3) float64 barycentric weights (may be slightly negative on the one-pixel
        ring extrapolated outside the chart so that bilinear sampling at boundary
        vertices stays exact for locally planar geometry).
    mask : (H, W) bool, True at ``pix``.
    samp_idx : (V, 4) int64 flat pixel indices of the bilinear taps of each vertex.
    samp_w : (V, 4) float64 bilinear weights, renormalised over ``mask``.
    """

    height: int
    width: int
    faces: np.ndarray
    pix: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    mask: np.ndarray
    samp_idx: np.ndarray
    samp_w: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.samp_idx.shape[0]


def _pixel_coords(uv: np.ndarray, height: int, width: int) -> np.ndarray:
    """(V, 2) UVs -> (V, 2) pixel-centre coordinates (x = column, y = row)."""
    uv = np.asarray(uv, np.float64)
    return np.stack([uv[:, 0] * width - 0.5, (1.0 - uv[:, 1]) * height - 0.5], axis=1)


def _barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentrics of points ``p`` (..., 2) in triangles ``a, b, c`` (..., 2) -> (..., 3)."""
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    den = np.where(np.abs(den) < 1e-300, 1e-300, den)
    l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    return np.stack([1.0 - l1 - l2, l1, l2], axis=-1)


def build_layout(faces: np.ndarray, uv: np.ndarray, size: int | tuple[int, int]) -> UVLayout:
    """Rasterise a UV layout: per-pixel triangle index and barycentrics.

    Parameters
    ----------
    faces : (F, 3) int
    uv : (V, 2) float in [0, 1] (OBJ convention, v up).
    size : int or (H, W)

    Returns
    -------
    UVLayout
        Pixels whose centre lies in a triangle carry its barycentrics; pixels within one
        pixel (8-neighbourhood) of the chart carry the extrapolated barycentrics of the
        nearest covered pixel's triangle.
    """
    h, w = (size, size) if np.isscalar(size) else tuple(int(s) for s in size)
    faces = np.asarray(faces, np.int64)
    uv = np.asarray(uv, np.float64)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise FacesynthError(f"faces: expected (F, 3) triangles, got {faces.shape}")
    if uv.ndim != 2 or uv.shape[1] != 2 or faces.max(initial=-1) >= len(uv) or faces.min(initial=0) < 0:
        raise FacesynthError(f"uv: expected (V, 2) with V > max face index, got {uv.shape}")
    if not np.isfinite(uv).all() or uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        raise FacesynthError("uv: expected finite coordinates in [0, 1]")
    pc = _pixel_coords(uv, h, w)
    tp = pc[faces]  # (F, 3, 2)
    x0 = np.clip(np.ceil(tp[..., 0].min(1)), 0, w - 1).astype(np.int64)
    x1 = np.clip(np.floor(tp[..., 0].max(1)), 0, w - 1).astype(np.int64)
    y0 = np.clip(np.ceil(tp[..., 1].min(1)), 0, h - 1).astype(np.int64)
    y1 = np.clip(np.floor(tp[..., 1].max(1)), 0, h - 1).astype(np.int64)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    tri_img = np.full(h * w, -1, np.int64)
    eps = -1e-9
    for dy in range(int(bh.max(initial=0))):
        for dx in range(int(bw.max(initial=0))):
            sel = np.nonzero((bw > dx) & (bh > dy))[0]
            if sel.size == 0:
                continue
            px, py = x0[sel] + dx, y0[sel] + dy
            t = tp[sel]
            lam = _barycentric(np.stack([px, py], 1).astype(np.float64), t[:, 0], t[:, 1], t[:, 2])
            inside = (lam >= eps).all(1)
            tri_img[py[inside] * w + px[inside]] = sel[inside]
    covered = (tri_img >= 0).reshape(h, w)
    if not covered.any():
        raise FacesynthError(f"uv: no triangle covers a pixel centre at {h}x{w}")
    ring = ndimage.binary_dilation(covered, structure=np.ones((3, 3), bool)) & ~covered
    _, (iy, ix) = ndimage.distance_transform_edt(~covered, return_indices=True)
    ring_pix = np.nonzero(ring.ravel())[0]
    tri_img[ring_pix] = tri_img[(iy.ravel() * w + ix.ravel())[ring_pix]]
    mask = (tri_img >= 0).reshape(h, w)
    pix = np.nonzero(mask.ravel())[0]
    tri = tri_img[pix]
    pxy = np.stack([pix % w, pix // w], 1).astype(np.float64)
    t = tp[tri]
    bary = _barycentric(pxy, t[:, 0], t[:, 1], t[:, 2])
    samp_idx, samp_w = _bilinear_taps(pc, mask, iy.ravel() * w + ix.ravel())
    return UVLayout(h, w, faces, pix, tri, bary, mask, samp_idx, samp_w)


def _bilinear_taps(pc: np.ndarray, mask: np.ndarray, nearest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear taps (V, 4) and weights renormalised over ``mask`` for pixel coords ``pc``;
    a vertex with no tap on the mask (e.g. one no face uses) takes the nearest covered pixel."""
    h, w = mask.shape
    x, y = pc[:, 0], pc[:, 1]  # half a pixel beyond the border: linear extrapolation
    xi = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    yi = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = x - xi, y - yi
    idx = np.stack([yi * w + xi, yi * w + xi + 1, (yi + 1) * w + xi, (yi + 1) * w + xi + 1], 1)
    wt = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    wt = wt * mask.ravel()[idx]
    s = wt.sum(1, keepdims=True)
    lone = s[:, 0] <= 1e-12
    idx[lone] = nearest[idx[lone, 0]][:, None]
    wt[lone], s[lone] = 0.25, 1.0
    return idx, wt / s


def rasterise(layout: UVLayout, vertices: np.ndarray) -> np.ndarray:
    """Geometry images of one mesh (V, 3) or a sequence (T, V, 3) -> (..., H, W, 3) float64.

    Pixels outside ``layout.mask`` are zero (see :func:`fill_outside`).
    """
    v = np.asarray(vertices, np.float64)
    if v.shape[-2:] != (layout.n_vertices, 3):
        raise FacesynthError(f"vertices: expected (..., {layout.n_vertices}, 3), got {v.shape}")
    lead = v.shape[:-2]
    v = v.reshape(-1, layout.n_vertices, 3)
    corners = v[:, layout.faces[layout.tri]]  # (T, P, 3, 3)
    vals = np.einsum("tpkc,pk->tpc", corners, layout.bary)
    out = np.zeros((v.shape[0], layout.height * layout.width, 3))
    out[:, layout.pix] = vals
    return out.reshape(*lead, layout.height, layout.width, 3)


def sample_vertices(layout: UVLayout, images: np.ndarray) -> np.ndarray:
    """Recover vertices from geometry images (..., H, W, 3) by bilinear sampling -> (..., V, 3)."""
    g = np.asarray(images, np.float64)
    lead = g.shape[:-3]
    g = g.reshape(-1, layout.height * layout.width, 3)
    taps = g[:, layout.samp_idx]  # (T, V, 4, 3)
    out = np.einsum("tvkc,vk->tvc", taps, layout.samp_w)
    return out.reshape(*lead, layout.n_vertices, 3)


def fill_outside(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Fill pixels outside ``mask`` smoothly by push-pull (Gortler et al. 1996).

    Parameters
    ----------
    image : (H, W, C) float
    mask : (H, W) bool

    Returns
    -------
    (H, W, C) float64, equal to ``image`` on the mask; outside it, a masked-average
    pyramid upsampled bilinearly, so the fill is smooth and cheap to code.
    """
    img = np.asarray(image, np.float64)
    m = np.asarray(mask, np.float64)
    if m.sum() == 0:
        raise FacesynthError("fill_outside: the mask is empty")
    levels = [(img * m[..., None], m)]
    while min(levels[-1][1].shape) > 1:
        s, mm = levels[-1]
        hh, ww = mm.shape
        hp, wp = hh + hh % 2, ww + ww % 2
        s = np.pad(s, ((0, hp - hh), (0, wp - ww), (0, 0)))
        mm = np.pad(mm, ((0, hp - hh), (0, wp - ww)))
        s = s.reshape(hp // 2, 2, wp // 2, 2, -1).sum((1, 3))
        mm = mm.reshape(hp // 2, 2, wp // 2, 2).sum((1, 3))
        levels.append((s, mm))
    s, mm = levels[-1]
    cur = s / np.maximum(mm, 1e-12)[..., None]
    for s, mm in reversed(levels[:-1]):
        hh, ww = mm.shape
        up = _upsample2(cur, hh, ww)
        own = s / np.maximum(mm, 1e-12)[..., None]
        wgt = np.clip(mm, 0, 1)[..., None]
        cur = wgt * own + (1 - wgt) * up
    return np.where(np.asarray(mask, bool)[..., None], img, cur)


def _upsample2(x: np.ndarray, hh: int, ww: int) -> np.ndarray:
    """Bilinear x2 upsampling of (h, w, C) to (hh, ww, C) with pixel-centre alignment."""
    h, w = x.shape[:2]
    ys = np.clip((np.arange(hh) + 0.5) / 2 - 0.5, 0, h - 1)
    xs = np.clip((np.arange(ww) + 0.5) / 2 - 0.5, 0, w - 1)
    y0 = np.floor(ys).astype(int)
    x0 = np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    fy, fx = (ys - y0)[:, None, None], (xs - x0)[None, :, None]
    top = x[y0][:, x0] * (1 - fx) + x[y0][:, x1] * fx
    bot = x[y1][:, x0] * (1 - fx) + x[y1][:, x1] * fx
    return top * (1 - fy) + bot * fy


@dataclass(frozen=True)
class Quantiser:
    """One shared 16-bit scale for x, y, z: ``q = round((p - lo) / diag * 65535)``.

    With ``diag = |hi - lo|`` (the bounding-box diagonal), PSNR of the uint16 images with
    peak 65535 equals vertex PSNR relative to the diagonal: ``20 log10(diag / rmse)``.
    """

    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)

    @property
    def diag(self) -> float:
        return float(np.linalg.norm(np.asarray(self.hi) - np.asarray(self.lo)))

    @classmethod
    def from_points(cls, points: np.ndarray, margin: float = 0.02) -> "Quantiser":
        """Bounding box of (..., 3) points grown by ``margin`` of its diagonal on each side."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        lo, hi = p.min(0), p.max(0)
        pad = margin * float(np.linalg.norm(hi - lo))
        return cls(lo - pad, hi + pad)

    def quantise(self, images: np.ndarray) -> np.ndarray:
        """(..., 3) float mesh units -> uint16 (clipped to [0, 65535])."""
        q = np.rint((np.asarray(images, np.float64) - self.lo) / self.diag * PEAK16)
        return np.clip(q, 0, PEAK16).astype(np.uint16)

    def dequantise(self, q: np.ndarray) -> np.ndarray:
        """uint16 (..., 3) -> float64 mesh units."""
        return np.asarray(q, np.float64) / PEAK16 * self.diag + self.lo


def geometry_video(layout: UVLayout, frames: np.ndarray, quantiser: Quantiser | None = None
                   ) -> tuple[np.ndarray, Quantiser]:
    """Mesh sequence (T, V, 3) -> filled uint16 geometry video (T, H, W, 3) and its quantiser."""
    frames = np.asarray(frames, np.float64)
    q = quantiser or Quantiser.from_points(frames)
    imgs = rasterise(layout, frames)
    out = np.empty(imgs.shape, np.uint16)
    for t in range(len(imgs)):
        out[t] = q.quantise(fill_outside(imgs[t], layout.mask))
    return out, q


def geometry_video_layouts(layouts: list[UVLayout], frames: list[np.ndarray], quantiser: Quantiser | None = None
                           ) -> tuple[np.ndarray, Quantiser, np.ndarray]:
    """A geometry video whose frames each have their own layout (scans of one sequence,
    each parameterised on its own): ``frames[t]`` (V_t, 3) over ``layouts[t]``.

    Returns the uint16 video (T, H, W, 3), the shared quantiser and the mask of the pixels
    covered in every frame (H, W)."""
    if len(layouts) != len(frames) or not layouts:
        raise FacesynthError(f"geometry_video_layouts: {len(layouts)} layouts for {len(frames)} frames")
    shape = (layouts[0].height, layouts[0].width)
    if any((lay.height, lay.width) != shape for lay in layouts):
        raise FacesynthError("geometry_video_layouts: every layout must have the same size")
    q = quantiser or Quantiser.from_points(np.concatenate([np.asarray(f, np.float64) for f in frames]))
    out = np.empty((len(frames), *shape, 3), np.uint16)
    mask = np.ones(shape, bool)
    for t, (lay, v) in enumerate(zip(layouts, frames, strict=True)):
        out[t] = q.quantise(fill_outside(rasterise(lay, v), lay.mask))
        mask &= lay.mask
    return out, q, mask


def vertex_solver(layout: UVLayout, eps: float = 1e-4):
    """Least-squares inverse of :func:`rasterise`: a callable (..., H, W, 3) -> (..., V, 3).

    The geometry image on the mask is linear in the vertices, ``G = A V`` (A: P x V sparse,
    the barycentric weights), so ``V = argmin |A V - G|^2 + eps |Lap V|^2`` (Lap: the
    umbrella graph Laplacian of the mesh, which fills in vertices whose triangles cover no
    pixel centre from their neighbours) recovers covered vertices almost exactly from an
    unquantised image and is the least-squares estimate for a coded one. The sparse normal
    matrix is factorised once (SuperLU); each frame is then three back-substitutions.
    """
    from scipy import sparse
    from scipy.sparse.linalg import factorized

    nv, npix = layout.n_vertices, len(layout.pix)
    rows = np.repeat(np.arange(npix), 3)
    a = sparse.csr_matrix((layout.bary.ravel(), (rows, layout.faces[layout.tri].ravel())), shape=(npix, nv))
    f = layout.faces
    i = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    j = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sparse.csr_matrix((np.ones(len(i)), (i, j)), shape=(nv, nv))
    adj.data[:] = 1.0  # edges shared by two triangles count once
    lap = sparse.diags(np.asarray(adj.sum(1)).ravel()) - adj
    solve = factorized((a.T @ a + eps * (lap.T @ lap) + 1e-9 * sparse.identity(nv)).tocsc())
    at = a.T.tocsr()

    def recover(images: np.ndarray) -> np.ndarray:
        g = np.asarray(images, np.float64)
        lead = g.shape[:-3]
        g = g.reshape(-1, layout.height * layout.width, 3)
        out = np.empty((len(g), nv, 3))
        for t in range(len(g)):
            rhs = at @ g[t, layout.pix]
            out[t] = np.stack([solve(rhs[:, k]) for k in range(3)], 1)
        return out.reshape(*lead, nv, 3)

    return recover
