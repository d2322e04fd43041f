"""The torch (exportable) forms of the talking head's numpy steps after the retargeting
(:mod:`facesynth.onnx.retarget_graph`), for :mod:`facesynth.onnx.talking_head`:

* :class:`FrameWarpGraph`: :class:`facesynth.runtime.fullframe.FrameWarp` (affine), the
  control points' motion and the piecewise-affine warp of the neutral frame, located by
  :class:`facesynth.model.warp.ToTarget`'s scanline coverage counting at the warp's grid
  nodes and bilinear between them;
* :class:`SeamGraph`: :func:`facesynth.compositing.blend_face` with a fixed feather (its
  alpha and band in the crop's pixels).

Landmarks of :data:`facesynth.retarget.RETARGET_SCHEMES` (the full-frame warp's control
points are placed on their iBUG-68 view).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.compositing import MIN_BAND, gaussian_kernel
from facesynth.geometry import mirror
from facesynth.landmarks import IBUG68, scheme_for_points
from facesynth.model.warp import ToTarget, invert_affine_t, similarity_to
from facesynth.onnx.retarget_graph import _apply, _const
from facesynth.ops import slice_by_tensor
from facesynth.runtime.fullframe import EYE_CORNERS, HEAD_POINTS, NOSE_TIP, FrameWarp, interpolation_weights, nose_offset

# the full-frame read's bands of rows (FrameWarpGraph.read): about this many pixels each, so
# that a band's per-pixel tensors stay in a core's cache
BAND_PIXELS = 1 << 16


class _Mesh:
    """The control points' triangulation in the neutral frame as ToTarget's reference frame
    (every frame pixel is texture)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray, size: tuple[int, int]):
        self.points, self.triangles, self.size = points, triangles, size

    def rasterise(self):
        return np.zeros(self.size, np.int64), None


class FrameWarpGraph(ToTarget):
    """:class:`FrameWarp` (affine) as tensor ops: avatar landmarks (B, P, 2) -> the warped
    neutral frame (B, 3, H, W), float values 0..255 rounded to integers.

    The control points' triangles are located at the nodes of FrameWarp's grid by
    :class:`ToTarget`'s scanline coverage counting on a canvas of one pixel per node (the
    control points scaled to it); a node covered once takes its triangle's affine map
    (output -> neutral-frame pixels), any other (a fold's gap or overlap) its own position.
    The node maps are upsampled bilinearly to every pixel as FrameWarp does (along x a MatMul
    by the interpolation matrix, along y two row gathers and a lerp), and
    the neutral frame is read there bilinearly, mirrored beyond its border (the nodes' maps
    reflected about the first and last pixel, as FrameWarp's)."""

    def __init__(self, fw: FrameWarp):
        w, h = fw.size
        nx, ny = fw.nodes
        wn, hn = len(nx), len(ny)
        span = np.tile(np.array([[wn, hn]], np.int64), (len(fw.triangles), 1))  # every node column
        super().__init__(_Mesh(fw.src, fw.triangles, (h, w)), span, canvas=(hn, wn))
        scheme = scheme_for_points(fw.n_points)
        self.view = None if scheme is IBUG68 else _const(scheme.ibug68_matrix())
        self.frame_size = (h, w)
        self.register_buffer("neutral68", _const(fw.neutral68[HEAD_POINTS]))
        self.register_buffer("neutral_nose", _const(nose_offset(fw.neutral68)[:, None]))  # (2, 1)
        extra = fw.src[fw.n_face:]
        self.register_buffer("extra", _const(extra))
        share, parallax = fw.shares()
        self.register_buffer("share", _const(share))
        self.register_buffer("parallax", _const(parallax))
        ring = fw._ring.astype(np.float32)[:, None]
        big = 1e9
        self.register_buffer("lo_clip", _const(np.where(ring > 0, [[1.0, -big]], [[-big, -big]])))
        self.register_buffer("hi_clip", _const(np.where(ring > 0, [[w - 2.0, h - 2.0]], [[big, big]])))
        self.register_buffer("bottom", _const(np.stack([np.zeros(len(extra)), fw.bottom], 1)))  # (K', 2) y of the bottom side
        self.register_buffer("frame_bottom", torch.tensor(float(h - 1) - fw.chin_margin))
        self.register_buffer("to_node", _const([[(wn - 1) / (w - 1), (hn - 1) / (h - 1)]]))  # frame px -> node units
        self.register_buffer("node_x", _const(nx))
        self.register_buffer("node_y", _const(ny[:, None]))
        # the frame as it is, uint8 (a quarter of float's memory traffic in the gathers), with one
        # pixel of its edge round it: maps a rounding error outside [0, W - 1] read it with a
        # weight of that error
        tex = np.pad(fw.frame, ((1, 1), (1, 1), (0, 0)), mode="edge")  # (H + 2, W + 2, 3)
        self.register_buffer("texture", torch.from_numpy(np.ascontiguousarray(tex.transpose(2, 0, 1).reshape(3, 1, -1))))
        self.tex_w = w + 2
        # the node maps' upsampling, as FrameWarp's: along x one MatMul by the (Wn, W)
        # interpolation matrix, along y two row gathers and a lerp
        (kx, fx), (ky, fy) = (interpolation_weights(n, len(nodes)) for n, nodes in ((w, nx), (h, ny)))
        up_x = np.zeros((wn, w), np.float32)
        np.add.at(up_x, (kx, np.arange(w)), 1.0 - fx)
        np.add.at(up_x, (kx + 1, np.arange(w)), fx)
        self.register_buffer("up_x", torch.from_numpy(up_x))
        self.register_buffer("up_k0", torch.from_numpy(ky.astype(np.int64)))
        self.register_buffer("up_k1", torch.from_numpy(ky.astype(np.int64) + 1))
        self.register_buffer("up_fy", _const(fy.reshape(1, 1, -1, 1)))
        self.register_buffer("box_lo", torch.zeros(2))
        self.register_buffer("box_hi", torch.tensor([float(wn), float(hn)]))
        self.register_buffer("cols_f", torch.arange(wn, dtype=torch.float32))
        self.register_buffer("rows_f", torch.arange(hn + 1, dtype=torch.float32))
        self.register_buffer("uv_max", torch.tensor([float(w - 1), float(h - 1)]).reshape(1, 2, 1, 1))
        # the nodes are located with FrameWarp's push of the right and bottom anchors (node units)
        self.register_buffer("outward", _const(fw.locate_push))

    def control_points(self, face: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) -> (B, K, 2) (FrameWarp.control_points)."""
        if self.view is not None:
            face = torch.matmul(self.view, face)  # the iBUG-68 view of a denser scheme
        s = similarity_to(self.neutral68.unsqueeze(0).expand(face.shape[0], -1, -1), face[:, HEAD_POINTS])
        nose = face[:, NOSE_TIP] - 0.5 * (face[:, EYE_CORNERS[0]] + face[:, EYE_CORNERS[1]])  # (B, 2)
        d = torch.matmul(s[:, :, :2], self.neutral_nose)[:, :, 0] - nose  # (B, 2) FrameWarp's parallax term
        moved = self.extra + self.share * (_apply(self.extra.unsqueeze(0), s[:, :, :2], s[:, :, 2]) - self.extra)
        moved = moved + self.parallax * d.unsqueeze(1)
        moved = torch.minimum(torch.maximum(moved, self.lo_clip), self.hi_clip)
        below = torch.clamp(face[:, :, 1].amax(1) - self.frame_bottom, min=0.0)  # (B,) a chin near the frame's bottom
        moved = moved + self.bottom * below[:, None, None]
        return torch.cat([face, moved], 1)

    def node_maps(self, face: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) -> (B, 2, Hn, Wn): the neutral-frame pixel (x, y) each grid node reads."""
        target = self.control_points(face) * self.to_node
        vert, e, _ = self.coordinates(target)
        maps, det = self.affine_maps(vert, e)
        ed = self.coordinates(target + self.outward)[2]
        lo, hi, cols, rows = self.box_lo, self.box_hi, self.cols_f, self.rows_f
        s = self.locate(ed, det, lo, hi, cols, rows).unsqueeze(1)  # (B, 1, Hn, Wn)
        u, v = self.source(maps, vert[:, :2], s, lo, hi, cols, rows[:-1])
        single = (s > self.code_base * 0.5) & (s < self.code_base * 2.0 + 1.0)  # one triangle: C + 1 .. C + T
        return torch.cat([torch.where(single, u, self.node_x + u * 0.0), torch.where(single, v, self.node_y + v * 0.0)], 1)

    def _upsampled(self, m: torch.Tensor) -> torch.Tensor:
        """(B, C, Hn, Wn) node values -> (B, C, H, W), bilinear as FrameWarp's maps: along x
        one MatMul by the (Wn, W) interpolation matrix, along y two row gathers and a lerp."""
        m = torch.matmul(m, self.up_x)
        m0, m1 = torch.index_select(m, 2, self.up_k0), torch.index_select(m, 2, self.up_k1)
        return m0 + self.up_fy * (m1 - m0)

    def maps(self, face: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) -> (B, 2, H, W): the neutral-frame pixel (x, y) each output pixel reads
        (FrameWarp.maps): the node maps mirrored at the frame's border, then upsampled."""
        return self._upsampled(mirror(self.node_maps(face), self.uv_max))

    def read(self, face: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) -> the warped neutral frame, uint8 (B, 3, H, W): read bilinearly (uint8
        taps, float lerps) and rounded.

        Band by band of rows (:data:`BAND_PIXELS` pixels each, fixed at export): each band's
        maps are upsampled from the node maps' x-upsampled rows, read and rounded while they
        are in the cache; the bands are then concatenated. Memory traffic, not arithmetic, sets
        a full-frame pass's cost."""
        m = torch.matmul(mirror(self.node_maps(face), self.uv_max), self.up_x)  # (B, 2, Hn, W)
        h = self.frame_size[0]
        edges = np.linspace(0, h, max(1, round(h * self.frame_size[1] / BAND_PIXELS)) + 1).round().astype(int)
        bands = []
        for r0, r1 in zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True):
            m0, m1 = torch.index_select(m, 2, self.up_k0[r0:r1]), torch.index_select(m, 2, self.up_k1[r0:r1])
            xy = m0 + self.up_fy[:, :, r0:r1] * (m1 - m0)  # (B, 2, rows, W)
            x, y = xy[:, 0:1], xy[:, 1:2]
            flx, fly = torch.floor(x), torch.floor(y)
            fx, fy = x - flx, y - fly
            # the index in float (exact below 2^24), then one Cast: an index chain the export's
            # int32 pass rewrites (facesynth.onnx.passes.int32_indices)
            base = (fly * float(self.tex_w) + (flx + float(self.tex_w + 1))).to(torch.int64)
            # one gather per tap and channel: the batch shares the texture (no copy per frame);
            # bilinear as two lerps along x, one along y, plus a half: the Cast rounds
            index = [(base + k).reshape(1, -1) for k in (0, 1, self.tex_w, self.tex_w + 1)]
            out = []
            for ch in range(3):
                t = [torch.gather(self.texture[ch], 1, i).reshape_as(fx).to(torch.float32) for i in index]
                top = t[0] + fx * (t[1] - t[0])
                out.append(top + (fy * (t[2] + fx * (t[3] - t[2]) - top) + 0.5))
            bands.append(torch.cat([c.to(torch.uint8) for c in out], 1))
        return torch.cat(bands, 2) if len(bands) > 1 else bands[0]

    def forward(self, face: torch.Tensor) -> torch.Tensor:  # noqa: D102  (a different signature from ToTarget's)
        return self.read(face).to(torch.float32)


def _reflect101(src: np.ndarray, n: int) -> np.ndarray:
    """Indices ``src`` mirrored into 0..n-1 (``BORDER_REFLECT_101``, as often as needed)."""
    if n == 1:
        return np.zeros_like(src)
    period = 2 * (n - 1)
    src = np.abs(np.mod(src, period))
    return np.where(src > n - 1, period - src, src)


# the seam blur's blocks of outputs (:class:`BandedBlur`): each block reads its own columns and
# the kernel's reach either side, so the cost per pixel is the block plus the kernel, not the
# crop's width
BLUR_BLOCK = 32


class BandedBlur(nn.Module):
    """The 1-D convolution along the second last axis (n long) with the centred kernel ``g``,
    mirrored beyond the ends (``BORDER_REFLECT_101``), as one Gather and one MatMul: the axis
    cut into blocks of :data:`BLUR_BLOCK` outputs, each gathered (whole rows) with the
    kernel's reach either side (the mirror in the gather's indices), times the constant
    (block, block + kernel - 1) band of the kernel. A block plus the kernel's length of
    multiply-adds per output, where a dense (n, n) matrix costs n."""

    def __init__(self, g: np.ndarray, n: int):
        super().__init__()
        p, b = len(g) // 2, min(BLUR_BLOCK, n)
        nb = -(-n // b)
        self.n = n
        src = np.arange(nb)[:, None] * b - p + np.arange(b + 2 * p)[None]  # (blocks, b + 2p) source rows
        self.register_buffer("index", torch.from_numpy(_reflect101(src, n).astype(np.int64)))
        k = np.zeros((b, b + 2 * p), np.float32)
        for o in range(b):
            k[o, o:o + 2 * p + 1] = g
        self.register_buffer("band", torch.from_numpy(k))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., n, W) -> the same shape, blurred along the n axis."""
        y = torch.matmul(self.band, x[..., self.index, :])  # (..., blocks, b, W)
        return y.flatten(-3, -2)[..., :self.n, :]


class SeamGraph(nn.Module):
    """:func:`facesynth.compositing.blend_face` (colour matching on) with a fixed feather
    of ``feather`` crop pixels: crop (B, C, Hc, Wc) in [0, 1], mask (B, 1, Hc, Wc), placement
    (B, 2, 3), the warped frame, uint8 (B, 3, H, W) (:meth:`FrameWarpGraph.read`) and the
    face's landmarks (B, P, 2) -> the composited frame, uint8 (B, 3, H, W).

    The alpha and the seam band are made in the crop's pixels (:func:`seam_layers`); the
    premultiplied face, alpha and band are placed in the frame bilinearly, inside the
    landmarks' bounding box of the batch grown by a crop pixel's size and 2 px (the placed
    face reaches no further), composed with the frame's box there, and put in its place by
    slices and concatenations of uint8: no full-frame float pass after the read."""

    CHANNELS = 5  # premultiplied face (3), alpha, band

    def __init__(self, feather: float, size: tuple[int, int], crop_size: tuple[int, int]):
        super().__init__()
        w, h = size
        self.feather = float(feather)
        self.r = max(1, int(math.ceil(self.feather)))
        g = gaussian_kernel(self.feather / 2)
        # the separable Gaussian (mirrored at the crop's edge, BORDER_REFLECT_101) as banded
        # MatMuls along rows (BandedBlur; along x on the transposed crop): a one-channel Conv
        # runs 16 channels wide in ONNX Runtime's blocked layout, and a dense (n, n) matrix
        # costs the crop's width per pixel (the auto reference width doubles it)
        ch, cw = crop_size  # (H, W), as the synthesis' canvas
        self.blur_x, self.blur_y = BandedBlur(g, cw), BandedBlur(g, ch)
        self.register_buffer("frame_max", torch.tensor([float(w), float(h)]))
        self.register_buffer("zero2", torch.zeros(2))

    @staticmethod
    def _erode_t(x: torch.Tensor, r: int) -> torch.Tensor:
        """Square (2r + 1) erosion of a {0, 1} (B, 1, h, w) map, the outside of the map
        counted as 0 (:func:`facesynth.compositing.seam_layers`), transposed: (B, 1, w, h). No
        hole (0) within r pixels, counted by running sums (CumSum), whose cost does not grow
        with r as MaxPool's does; both along the second last axis (a CumSum along the last
        axis runs several times slower in ONNX Runtime), the map transposed between them."""
        k = 2 * r + 1
        c = torch.cumsum(F.pad(1.0 - x, (0, 0, r + 1, r), value=1.0), 2)
        holes = (c[:, :, k:] - c[:, :, :-k]).transpose(2, 3)  # holes per column window, (B, 1, w, h)
        c = torch.cumsum(F.pad(holes, (0, 0, r + 1, r), value=float(k)), 2)
        return ((c[:, :, k:] - c[:, :, :-k]) < 0.5).to(x.dtype)

    def layers(self, crop: torch.Tensor, mask: torch.Tensor, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 5, Hc, Wc) premultiplied face (times ``scale``), alpha, band (:func:`seam_layers`)
        and the face's mean colour in the band (B, 3)."""
        hard = (mask > 0.5).to(crop.dtype)
        alpha = self.blur_y(self.blur_x(self._erode_t(hard, self.r)).transpose(2, 3)) * hard
        band = hard * (1.0 - self._erode_t(hard, 2 * self.r).transpose(2, 3))
        # the band's colour sums as one MatMul (B, 3, N) x (B, N, 1): no full-crop product
        sums = torch.matmul(crop.flatten(2), band.reshape(band.shape[0], -1, 1))[:, :, 0]
        face_mean = sums / torch.clamp(band.sum((2, 3)), min=1.0)
        return torch.cat([crop * (alpha * scale if scale != 1.0 else alpha), alpha, band], 1), face_mean

    def _bilinear(self, images: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> list[torch.Tensor]:
        """(B, 5, h, w) images read at (B, 1, Hb, Wb) pixel positions u, v -> five (B, 1, Hb, Wb):
        bilinear, zero outside (``cv2.warpAffine``'s constant border); one element gather per
        tap of all the channels."""
        h, w = int(images.shape[2]), int(images.shape[3])
        flat = F.pad(images, (1, 2, 1, 2)).flatten(2)  # (B, 5, R), one zero pixel round it (two after)
        u = torch.clamp(u, -1.0, float(w)) + 1.0  # padded pixels
        v = torch.clamp(v, -1.0, float(h)) + 1.0
        fu, fv = torch.floor(u), torch.floor(v)
        fx, fy = u - fu, v - fv
        base = (fv * float(w + 3) + fu).to(torch.int64).flatten(1)  # (B, N), an int32 index chain once exported
        index = [base + k for k in (0, 1, w + 3, w + 4)]
        out = []
        for ch in range(self.CHANNELS):
            t = [torch.gather(flat[:, ch], 1, i).reshape_as(fx) for i in index]
            top = t[0] + fx * (t[1] - t[0])
            out.append(top + fy * (t[2] + fx * (t[3] - t[2]) - top))
        return out

    def forward(self, crop: torch.Tensor, mask: torch.Tensor, placement: torch.Tensor, frame: torch.Tensor,
                face: torch.Tensor) -> torch.Tensor:
        """``frame``: the warped frame, uint8 (B, 3, H, W) (FrameWarpGraph.read) -> the
        composited frame, uint8 (B, 3, H, W)."""
        if crop.shape[1] == 1:
            crop = torch.cat([crop, crop, crop], 1)
        layers, face_mean = self.layers(crop, mask, 255.0)  # the premultiplied face in 0..255, as the frame
        # the box: the landmarks' bounding box grown by the largest crop pixel (placed) and 2 px
        reach = torch.ceil(torch.sqrt((placement[:, :, 0] ** 2).sum(1)).amax()) + 2.0
        xy = face.reshape(-1, 2)
        lo = torch.clamp(torch.floor(xy.amin(0)) - reach, min=0.0)
        hi = torch.minimum(torch.ceil(xy.amax(0)) + reach + 1.0, self.frame_max)
        hi = torch.maximum(hi, lo + 1.0)
        xs, ys = torch.arange(lo[0], hi[0]), torch.arange(lo[1], hi[1])
        inv = invert_affine_t(placement).reshape(-1, 6, 1, 1)  # frame -> crop pixels
        xr, yr = xs.reshape(1, 1, 1, -1), ys.reshape(1, 1, -1, 1)
        inv = inv.unsqueeze(2)  # (B, 6, 1, 1, 1)
        u = inv[:, 0] * xr + (inv[:, 1] * yr + inv[:, 2])  # (B, 1, Hb, Wb) box pixels in the crop
        v = inv[:, 3] * xr + (inv[:, 4] * yr + inv[:, 5])
        *pre, alpha, band = self._bilinear(layers, u, v)
        # [y0, x0, y1, x1] of the box, and of the frame's parts round it
        y0x0, y1x1 = lo.flip(0).to(torch.int64), hi.flip(0).to(torch.int64)
        box = slice_by_tensor(frame, torch.cat([y0x0, y1x1])).to(torch.float32)  # the warped frame's box
        bg = [box[:, k:k + 1] for k in range(3)]
        n = band.sum((2, 3))  # (B, 1)
        sums = torch.cat([(c * band).sum((2, 3)) for c in bg], 1)  # (B, 3)
        shift = sums / torch.clamp(n, min=1.0) - face_mean * 255.0
        shift = torch.where(n > MIN_BAND, shift, shift * 0.0)[:, :, None, None]
        # face + alpha shift + (1 - alpha) frame, plus a half: rounded by the Cast
        inner = torch.cat([torch.clamp(p + (c + 0.5) + alpha * (shift[:, k:k + 1] - c), 0.0, 255.0).to(torch.uint8)
                           for k, (p, c) in enumerate(zip(pre, bg, strict=True))], 1)
        # the frame with the box replaced: rows above it, the box's rows, rows below it
        zero, size = self.zero2.to(torch.int64), self.frame_max.flip(0).to(torch.int64)  # [0, 0], [H, W]
        cut = torch.cat([y0x0[:1], size[1:]])  # [y0, W]
        top = slice_by_tensor(frame, torch.cat([zero, cut]))
        left = slice_by_tensor(frame, torch.cat([y0x0[:1], zero[:1], y1x1[:1], y0x0[1:]]))
        right = slice_by_tensor(frame, torch.cat([y0x0[:1], y1x1[1:], y1x1[:1], size[1:]]))
        bottom = slice_by_tensor(frame, torch.cat([y1x1[:1], zero[:1], size]))
        return torch.cat([top, torch.cat([left, inner, right], 3), bottom], 2)
