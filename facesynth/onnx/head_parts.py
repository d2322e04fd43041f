"""The torch (exportable) forms of the talking head's numpy steps, for
:mod:`facesynth.onnx.talking_head`:

* :class:`RetargetGraph`: :class:`facesynth.retarget.Retargeter` (relative motion) and
  :meth:`facesynth.retarget.ShapeSpace.project`, with the driver's neutral a graph input
  (its FAP units, face axes and rigid-point fits are computed in the graph);
* :class:`FrameWarpGraph`: :class:`facesynth.runtime.fullframe.FrameWarp` (affine), the
  control points' motion and the piecewise-affine warp of the neutral frame, located by
  :class:`facesynth.model.warp.ToTarget`'s scanline coverage counting at the warp's grid
  nodes and bilinear between them;
* :class:`SeamGraph`: :func:`facesynth.runtime.blend.blend_face` with a fixed feather (its
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

from facesynth.faps import FAPU_NAMES, FEATURE_POINTS, face_axes, fapu
from facesynth.landmarks import IBUG68, LandmarkScheme, ibug68_view, scheme_for_points
from facesynth.model.warp import invert_affine_t, similarity_to
from facesynth.model.warp_target import ToTarget
from facesynth.ops import pad_by_tensor, slice_by_tensor
from facesynth.retarget import POINT_UNITS, ShapeSpace, closing_pairs, eye_patches, iris_diameter, point_units, rigid_points
from facesynth.runtime.blend import MIN_BAND, gaussian_kernel
from facesynth.runtime.fullframe import HEAD_POINTS, FrameWarp


def _const(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, np.float32))


def _apply(points: torch.Tensor, lin: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(B, K, 2) points through (B, 2, 2) linear parts and (B, 2) translations."""
    return torch.matmul(points, lin.transpose(1, 2)) + t.unsqueeze(1)


def _scatter(index: list[int], n: int) -> torch.Tensor:
    """(n, len(index)) 0/1 matrix putting rows at ``index`` (a MatMul instead of ScatterND)."""
    m = np.zeros((n, len(index)), np.float32)
    m[index, np.arange(len(index))] = 1.0
    return torch.from_numpy(m)


def _similarity(ca: torch.Tensor, sa: torch.Tensor) -> torch.Tensor:
    """(B,) scale-cos, scale-sin -> (B, 2, 2) [[ca, -sa], [sa, ca]]."""
    return torch.stack([torch.stack([ca, -sa], -1), torch.stack([sa, ca], -1)], 1)


class RetargetGraph(nn.Module):
    """Driver landmarks (B, P, 2) and the driver's neutral (P, 2) -> avatar landmarks
    (B, P, 2): the steps of :class:`facesynth.retarget.Retargeter` (relative motion, head
    motion on) and the shape clamp of ``shape_space`` (eyelids kept), for a scheme of
    :data:`facesynth.retarget.RETARGET_SCHEMES` (FAP units and face axes on its iBUG-68
    view; with irises, IRISD from the iris diameters)."""

    def __init__(self, avatar_neutral: np.ndarray, shape_space: ShapeSpace | None, scheme: LandmarkScheme = IBUG68):
        super().__init__()
        an = np.asarray(avatar_neutral, np.float64)
        view = np.eye(len(an)) if scheme is IBUG68 else scheme.ibug68_matrix()  # (68, P)
        ids = list(FEATURE_POINTS)
        fp = np.zeros((len(ids), 68))
        for i, k in enumerate(ids):
            fp[i, list(FEATURE_POINTS[k])] = 1.0 / len(FEATURE_POINTS[k])
        # the feature points fapu and face_axes read: 3.5, 3.6, 9.15, 2.2, 8.3, 8.4, 3.1, 3.3, 3.2, 3.4
        fp = fp[[ids.index(k) for k in ("3.5", "3.6", "9.15", "2.2", "8.3", "8.4", "3.1", "3.3", "3.2", "3.4")]]
        self.register_buffer("fp", _const(fp @ view))
        a68 = ibug68_view(an)
        self.register_buffer("an", _const(an))
        ratio_a = fapu(a68)
        self.iris = [[int(i) for i in scheme.region(side)] for side in ("right_iris", "left_iris")] \
            if "irises" in scheme.regions else None
        if self.iris is not None:  # IRISD: the iris diameters' ratio (retarget.iris_diameter)
            ratio_a[FAPU_NAMES.index("IRISD")] = iris_diameter(scheme, an)
            put = np.zeros(len(FAPU_NAMES))
            put[FAPU_NAMES.index("IRISD")] = 1.0
            self.register_buffer("iris_put", _const(put))
        self.register_buffer("fapu_a", _const(ratio_a))
        self.register_buffer("axes_a", _const(face_axes(a68)))
        units = POINT_UNITS if scheme is IBUG68 else point_units(scheme, an)
        onehot = np.zeros((2, len(FAPU_NAMES), len(an)))  # ratio (5,) -> per-point scale (P,) of each axis
        for ax in range(2):
            onehot[ax, units[:, ax], np.arange(len(an))] = 1.0
        self.register_buffer("units", _const(onehot))
        self.rigid = rigid_points(scheme)
        self.register_buffer("an_rigid", _const(an[self.rigid]))
        up, lo = closing_pairs(scheme)
        self.shut_up, self.shut_lo = [int(i) for i in up], [int(i) for i in lo]
        self.register_buffer("put_up", _scatter(self.shut_up, len(an)))
        self.register_buffer("put_lo", _scatter(self.shut_lo, len(an)))
        self.space = shape_space
        if shape_space is not None:
            s = shape_space
            self.register_buffer("mu", _const(s._mu))
            self.register_buffer("w", _const(s._w))
            self.register_buffer("ct", _const(s._ct))
            self.register_buffer("off", _const(s._off))
            self.register_buffer("limit", _const(s.limit))
            self.register_buffer("comp", _const(s.components))
            self.eyes = [([int(i) for i in idx], int(c0), int(c1)) for idx, c0, c1 in eye_patches(scheme)]
            for k, (idx, _, _) in enumerate(self.eyes):
                self.register_buffer(f"put_eye{k}", _scatter(idx, len(an)))
            self.keep_eyes = bool(s.keep_eyes)

    def _iris_diameter(self, face: torch.Tensor) -> torch.Tensor:
        """:func:`facesynth.retarget.iris_diameter` of a (P, 2) face."""
        out = []
        for idx in self.iris:
            d = face[idx[1:]] - face[idx[0]]
            out.append(2.0 * torch.sqrt((d * d).sum(-1)).mean())
        return 0.5 * (out[0] + out[1])

    def forward(self, driver: torch.Tensor, neutral: torch.Tensor) -> torch.Tensor:
        f = torch.matmul(self.fp, neutral)  # (10, 2) feature points of the driver's neutral
        xd = f[0] - f[1]
        es = torch.sqrt((xd * xd).sum())
        xd = xd / es
        down = torch.stack([-xd[1], xd[0]])
        pupils = 0.5 * (f[0] + f[1])
        iris = 0.5 * (torch.sqrt(((f[6] - f[7]) ** 2).sum()) + torch.sqrt(((f[8] - f[9]) ** 2).sum()))
        fapu_d = torch.stack([es, ((f[2] - pupils) * down).sum(), ((f[3] - f[2]) * down).sum(),
                              torch.sqrt(((f[4] - f[5]) ** 2).sum()), iris]) / 1024.0
        if self.iris is not None:
            fapu_d = fapu_d + self.iris_put * (self._iris_diameter(neutral) - fapu_d)
        ratio = self.fapu_a / fapu_d  # (5,)
        axes_d = torch.stack([xd, down])  # (2, 2) rows x, down
        scale = torch.matmul(ratio, self.units).t()  # (P, 2) per point and driver axis
        # e[p, i, k] = sum_j axes_d[j, i] scale[p, j] axes_a[j, k]
        e0 = torch.matmul(scale * axes_d[:, 0], self.axes_a)  # (P, 2)
        e1 = torch.matmul(scale * axes_d[:, 1], self.axes_a)
        # head pose: similarity driver neutral -> frame on the rigid points
        dn = neutral[self.rigid]
        dn_mu = dn.mean(0)
        dc = dn - dn_mu
        r = driver[:, self.rigid]
        r_mu = r.mean(1)
        rc = r - r_mu.unsqueeze(1)
        var = (dc * dc).sum()
        ca = (rc * dc).sum((1, 2)) / var
        sa = (rc[..., 1] * dc[:, 0] - rc[..., 0] * dc[:, 1]).sum(1) / var
        lin = _similarity(ca, sa)  # (B, 2, 2)
        t = r_mu - torch.matmul(lin, dn_mu)  # (B, 2)
        inv_t = lin / (ca * ca + sa * sa)[:, None, None]
        disp = torch.matmul(driver - t.unsqueeze(1), inv_t) - neutral
        expr = self.an + disp[..., 0:1] * e0 + disp[..., 1:2] * e1
        expr = self._uncrossed(expr, self.axes_a[1])
        # head motion C P C^-1 around the avatar's neutral placement
        c = similarity_to(dn.unsqueeze(0), self.an_rigid)[0]  # (2, 3) driver -> avatar
        c_lin, c_t = c[:, :2], c[:, 2]
        det = c_lin[0, 0] * c_lin[1, 1] - c_lin[0, 1] * c_lin[1, 0]
        c_inv = torch.stack([torch.stack([c_lin[1, 1], -c_lin[0, 1]]), torch.stack([-c_lin[1, 0], c_lin[0, 0]])]) / det
        m_lin = torch.matmul(torch.matmul(c_lin, lin), c_inv)
        m_t = torch.matmul(c_lin, (t - torch.matmul(lin, torch.matmul(c_inv, c_t))).unsqueeze(-1))[..., 0] + c_t
        out = _apply(expr, m_lin, m_t)
        if self.space is None:
            return out
        down = torch.matmul(m_lin, self.axes_a[1])  # (B, 2): the avatar's down axis, moved with the head
        down = down / torch.sqrt((down * down).sum(-1, keepdim=True))
        return self._uncrossed(self._project(out), down.unsqueeze(1))

    def _uncrossed(self, expr: torch.Tensor, down: torch.Tensor) -> torch.Tensor:  # Retargeter._uncrossed
        up, lo = expr[:, self.shut_up], expr[:, self.shut_lo]
        du, dl = (up * down).sum(-1, keepdim=True), (lo * down).sum(-1, keepdim=True)
        cross = du > dl
        mid = 0.5 * (du + dl)
        d_up = torch.where(cross, (mid - du) * down, up * 0.0)
        d_lo = torch.where(cross, (mid - dl) * down, lo * 0.0)
        return expr + torch.matmul(self.put_up, d_up) + torch.matmul(self.put_lo, d_lo)

    def _project(self, x: torch.Tensor) -> torch.Tensor:
        n = x.shape[1]
        mo = x.mean(1, keepdim=True)
        xc = x - mo
        var = (xc * xc).sum((1, 2))
        ab = torch.matmul(xc.flatten(1), self.w) / var.unsqueeze(1)
        ca, sa = ab[:, 0], ab[:, 1]
        aligned = _apply(xc, _similarity(ca, sa), self.mu.expand_as(ab))
        b = torch.matmul(aligned.flatten(1), self.ct) - self.off
        excess = torch.clamp(b - self.limit, min=0.0) + torch.clamp(b + self.limit, max=0.0)
        rec = aligned - torch.matmul(excess, self.comp).reshape(-1, n, 2)
        if self.keep_eyes:
            rec = self._restore_eyes(rec, aligned)
        k = (ca * ca + sa * sa)
        inv = _similarity(ca / k, -sa / k)
        return torch.matmul(rec - self.mu, inv.transpose(1, 2)) + mo

    def _restore_eyes(self, rec: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
        """Each eye's contour of ``before`` onto ``rec``'s corners (retarget._restore_local)."""
        out = rec
        for k, (idx, c0, c1) in enumerate(self.eyes):
            s0, s1, d0, d1 = before[:, c0], before[:, c1], rec[:, c0], rec[:, c1]
            ds, dd = s1 - s0, d1 - d0
            n = (ds * ds).sum(-1)
            kr = (dd[:, 0] * ds[:, 0] + dd[:, 1] * ds[:, 1]) / n  # k = dd / ds (complex)
            ki = (dd[:, 1] * ds[:, 0] - dd[:, 0] * ds[:, 1]) / n
            moved = _apply(before[:, idx] - s0.unsqueeze(1), _similarity(kr, ki), d0)
            out = out + torch.matmul(getattr(self, f"put_eye{k}"), moved - rec[:, idx])
        return out


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
    The node maps are upsampled bilinearly to every pixel (Resize, ``align_corners``), and
    the neutral frame is read there bilinearly, its border replicated (as ``cv2.remap``)."""

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
        extra = fw.src[fw.n_face:]
        self.register_buffer("extra", _const(extra))
        self.register_buffer("share", _const(fw._share))
        ring = fw._ring.astype(np.float32)[:, None]
        big = 1e9
        self.register_buffer("lo_clip", _const(np.where(ring > 0, [[1.0, -big]], [[-big, -big]])))
        self.register_buffer("hi_clip", _const(np.where(ring > 0, [[w - 2.0, h - 2.0]], [[big, big]])))
        self.register_buffer("to_node", _const([[(wn - 1) / (w - 1), (hn - 1) / (h - 1)]]))  # frame px -> node units
        self.register_buffer("node_x", _const(nx))
        self.register_buffer("node_y", _const(ny[:, None]))
        tex = np.pad(fw.frame.astype(np.float32), ((0, 1), (0, 1), (0, 0)), mode="edge")  # (H + 1, W + 1, 3)
        self.register_buffer("texture", torch.from_numpy(np.ascontiguousarray(tex.transpose(2, 0, 1).reshape(3, 1, -1))))
        self.register_buffer("quad", torch.tensor([0, 1, w + 1, w + 2]).reshape(4, 1, 1))
        self.register_buffer("box_lo", torch.zeros(2))
        self.register_buffer("box_hi", torch.tensor([float(wn), float(hn)]))
        self.register_buffer("cols_f", torch.arange(wn, dtype=torch.float32))
        self.register_buffer("rows_f", torch.arange(hn + 1, dtype=torch.float32))
        self.register_buffer("uv_max", torch.tensor([float(w - 1), float(h - 1)]).reshape(1, 2, 1, 1))
        self.tex_w = w + 1
        # the nodes are located with FrameWarp's push of the right and bottom anchors (node units)
        self.register_buffer("outward", _const(fw.locate_push))

    def control_points(self, face: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) -> (B, K, 2) (FrameWarp.control_points)."""
        if self.view is not None:
            face = torch.matmul(self.view, face)  # the iBUG-68 view of a denser scheme
        s = similarity_to(self.neutral68.unsqueeze(0).expand(face.shape[0], -1, -1), face[:, HEAD_POINTS])
        moved = self.extra + self.share * (_apply(self.extra.unsqueeze(0), s[:, :, :2], s[:, :, 2]) - self.extra)
        moved = torch.minimum(torch.maximum(moved, self.lo_clip), self.hi_clip)
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

    def forward(self, face: torch.Tensor) -> torch.Tensor:  # noqa: D102  (a different signature from ToTarget's)
        uv = F.interpolate(self.node_maps(face), size=self.frame_size, mode="bilinear", align_corners=True)
        uv = torch.minimum(torch.clamp(uv, min=0.0), self.uv_max)  # border replicated
        fl = torch.floor(uv)
        fx, fy = uv[:, 0:1] - fl[:, 0:1], uv[:, 1:2] - fl[:, 1:2]  # (B, 1, H, W)
        # the index in float (exact below 2^24), then one Cast: an index chain the export's
        # int32 pass rewrites (facesynth.onnx.passes.int32_indices)
        base = (fl[:, 1:2] * float(self.tex_w) + fl[:, 0:1]).to(torch.int64)
        # one gather per tap and channel: the batch shares the texture (no copy per frame), and
        # no split of a (B, 4, H, W) gather; bilinear as two lerps along x, one along y
        index = [(base + k).reshape(1, -1) for k in (0, 1, self.tex_w, self.tex_w + 1)]
        out = []
        for ch in range(3):
            t = [torch.gather(self.texture[ch], 1, i).reshape_as(fx) for i in index]
            top = t[0] + fx * (t[1] - t[0])
            out.append(top + fy * (t[2] + fx * (t[3] - t[2]) - top))
        return torch.floor(torch.cat(out, 1) + 0.5)


class SeamGraph(nn.Module):
    """:func:`facesynth.runtime.blend.blend_face` (colour matching on) with a fixed feather
    of ``feather`` crop pixels: crop (B, C, Hc, Wc) in [0, 1], mask (B, 1, Hc, Wc), placement
    (B, 2, 3), the warped frame (B, 3, H, W) 0..255 and the face's landmarks (B, P, 2) ->
    (B, 3, H, W) 0..255 integer values.

    The alpha and the seam band are made in the crop's pixels (:func:`seam_layers`); the
    premultiplied face, alpha and band are placed in the frame bilinearly, inside the
    landmarks' bounding box of the batch grown by a crop pixel's size and 2 px (the placed
    face reaches no further)."""

    CHANNELS = 5  # premultiplied face (3), alpha, band

    def __init__(self, feather: float, size: tuple[int, int], crop_size: tuple[int, int]):
        super().__init__()
        w, h = size
        self.feather = float(feather)
        self.r = max(1, int(math.ceil(self.feather)))
        g = gaussian_kernel(self.feather / 2)
        self.k = k = len(g)
        self.register_buffer("gx", torch.from_numpy(g.copy()).reshape(1, 1, 1, k))
        self.register_buffer("gy", torch.from_numpy(g.copy()).reshape(1, 1, k, 1))
        self.register_buffer("frame_max", torch.tensor([float(w), float(h)]))
        self.register_buffer("zero2", torch.zeros(2))

    @staticmethod
    def _erode(x: torch.Tensor, r: int) -> torch.Tensor:
        """Square (2r + 1) erosion of a {0, 1} (B, 1, h, w) map, the outside of the map
        counted as 0 (:func:`facesynth.runtime.blend.seam_layers`): no hole (0) within r
        pixels, counted by running sums (CumSum), whose cost does not grow with r as
        MaxPool's does."""
        k = 2 * r + 1
        c = torch.cumsum(F.pad(1.0 - x, (r + 1, r), value=1.0), 3)
        holes = c[..., k:] - c[..., :-k]
        c = torch.cumsum(F.pad(holes, (0, 0, r + 1, r), value=float(k)), 2)
        return ((c[:, :, k:] - c[:, :, :-k]) < 0.5).to(x.dtype)

    def layers(self, crop: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 5, Hc, Wc) premultiplied face, alpha, band (:func:`seam_layers`) and the face's
        mean colour in the band (B, 3)."""
        hard = (mask > 0.5).to(crop.dtype)
        p = self.k // 2
        a = F.conv2d(F.pad(self._erode(hard, self.r), (p, p, 0, 0), mode="reflect"), self.gx)
        alpha = F.conv2d(F.pad(a, (0, 0, p, p), mode="reflect"), self.gy) * hard
        band = hard * (1.0 - self._erode(hard, 2 * self.r))
        face_mean = (crop * band).sum((2, 3)) / torch.clamp(band.sum((2, 3)), min=1.0)
        return torch.cat([crop * alpha, alpha, band], 1), face_mean

    def _bilinear(self, images: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """(B, 5, h, w) images read at (B, 1, Hb, Wb) pixel positions u, v -> (B, 5, Hb, Wb):
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
        return torch.cat(out, 1)

    def forward(self, crop: torch.Tensor, mask: torch.Tensor, placement: torch.Tensor, frame: torch.Tensor,
                face: torch.Tensor) -> torch.Tensor:
        if crop.shape[1] == 1:
            crop = torch.cat([crop, crop, crop], 1)
        layers, face_mean = self.layers(crop, mask)
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
        placed = self._bilinear(layers, u, v)
        pre, alpha, band = placed[:, :3], placed[:, 3:4], placed[:, 4:5]
        bg255 = slice_by_tensor(frame, torch.cat([lo.flip(0), hi.flip(0)]).to(torch.int64))
        bg = bg255 / 255.0
        n = band.sum((2, 3))  # (B, 1)
        shift = (bg * band).sum((2, 3)) / torch.clamp(n, min=1.0) - face_mean
        shift = torch.where(n > MIN_BAND, shift, shift * 0.0)[:, :, None, None]
        blended = pre + alpha * shift + (1.0 - alpha) * bg
        box = torch.clamp(torch.floor(blended * 255.0 + 0.5), 0.0, 255.0)
        pads = torch.cat([self.zero2, lo.flip(0), self.zero2, (self.frame_max - hi).flip(0)]).to(torch.int64)
        return frame + pad_by_tensor(box - bg255, pads)
