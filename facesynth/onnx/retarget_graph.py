"""The talking head's retargeting as tensor ops, for :mod:`facesynth.onnx.talking_head`:
:class:`RetargetGraph` is :class:`facesynth.retarget.Retargeter` (relative motion) and
:meth:`facesynth.shape_space.ShapeSpace.project`, with the driver's neutral a graph input (its
FAP units, face axes and rigid-point fits are computed in the graph), for the landmarks of
:data:`facesynth.retarget.RETARGET_SCHEMES`; and the small tensor helpers the other parts
(:mod:`facesynth.onnx.head_parts`) share.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from facesynth.faps import FAPU_NAMES, FEATURE_POINTS, face_axes, fapu
from facesynth.landmarks import IBUG68, LandmarkScheme, eye_lids, ibug68_view
from facesynth.model.warp import similarity_to
from facesynth.retarget import POINT_UNITS, closing_pairs, iris_diameter, point_units, rigid_points, shift_bounds
from facesynth.shape_space import ShapeSpace, eye_patches


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
    motion on) and the shape clamp of ``shape_space`` (eyelids kept, then the part outside the
    components and each eye's opening capped when the space has those bounds), for a scheme of
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
        bounds = shift_bounds(shape_space, an)  # the head's travel (Retargeter, step 4); none: unbounded
        self.bounded = bounds is not None
        if self.bounded:
            self.register_buffer("centre", _const(an[self.rigid].mean(0)))
            self.register_buffer("shift_lo", _const(bounds[0]))
            self.register_buffer("shift_hi", _const(bounds[1]))
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
            self.cap_norm = s.param_norm_max is not None
            if self.cap_norm:
                self.register_buffer("norm_max", _const(s.param_norm_max))
            self.cap_rest = s.residual_max is not None
            if self.cap_rest:
                self.register_buffer("mean_flat", _const(s.mean))
                self.register_buffer("rest_max", _const(s.residual_max))
            self.eyes = [([int(i) for i in idx], int(c0), int(c1)) for idx, c0, c1 in eye_patches(scheme)]
            for k, (idx, _, _) in enumerate(self.eyes):
                self.register_buffer(f"put_eye{k}", _scatter(idx, len(an)))
            self.keep_eyes = bool(s.keep_eyes)
            self.cap_eyes = s.eye_open_max is not None
            if self.cap_eyes:  # both eyes at once: (2, n) contour and iris, (2,) corners, (2, k) facing lids
                self.register_buffer("eye_cap", _const(np.asarray(s.eye_open_max)[:, None]))
                self.eye_idx = torch.tensor([idx for idx, _, _ in self.eyes])
                self.eye_c0 = torch.tensor([c0 for _, c0, _ in self.eyes])
                self.eye_c1 = torch.tensor([c1 for _, _, c1 in self.eyes])
                lids = eye_lids(scheme)
                self.lid_up, self.lid_lo = (torch.from_numpy(np.stack([pair[j] for pair in lids])) for j in (0, 1))
                self.register_buffer("put_eyes", _scatter(self.eye_idx.reshape(-1).tolist(), len(an)))

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
        if self.bounded:  # the head's travel (Retargeter, step 4)
            shift = torch.matmul(m_lin, self.centre) + m_t - self.centre  # (B, 2)
            m_t = m_t + torch.minimum(torch.maximum(shift, self.shift_lo), self.shift_hi) - shift
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
        c = torch.minimum(torch.maximum(b, -self.limit), self.limit)
        if self.cap_norm:  # into the ellipsoid of norm norm_max (ShapeSpace._clamped)
            norm = torch.sqrt(((c / self.limit) ** 2).sum(-1, keepdim=True))
            c = c * torch.clamp(self.norm_max / torch.clamp(norm, min=1e-30), max=1.0)
        rec = aligned - torch.matmul(b - c, self.comp).reshape(-1, n, 2)
        if self.cap_rest:  # what the components do not span, scaled down to rest_max (ShapeSpace.project)
            rest = aligned.flatten(1) - self.mean_flat - torch.matmul(b, self.comp)  # (B, 2P)
            norm = torch.sqrt((rest * rest).sum(-1, keepdim=True))
            shrink = torch.clamp(1.0 - self.rest_max / torch.clamp(norm, min=1e-30), min=0.0)
            rec = rec - (shrink * rest).reshape(-1, n, 2)
        if self.keep_eyes:
            rec = self._restore_eyes(rec, aligned)
        if self.cap_eyes:
            rec = self._cap_eyes(rec)
        k = (ca * ca + sa * sa)
        inv = _similarity(ca / k, -sa / k)
        return torch.matmul(rec - self.mu, inv.transpose(1, 2)) + mo

    def _restore_eyes(self, rec: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
        """Each eye's contour of ``before`` onto ``rec``'s corners (shape_space._restore_local)."""
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

    def _cap_eyes(self, rec: torch.Tensor) -> torch.Tensor:
        """Each eye wider than its cap squashed towards its corner line (shape_space._cap_eyes),
        both eyes in one pass."""
        c0 = rec[:, self.eye_c0]  # (B, 2 eyes, 2)
        axis = rec[:, self.eye_c1] - c0
        width = torch.clamp(torch.sqrt((axis * axis).sum(-1, keepdim=True)), min=1e-12)  # (B, 2, 1)
        normal = torch.stack([-axis[..., 1], axis[..., 0]], -1) / width  # (B, 2, 2)
        gap = torch.abs(((rec[:, self.lid_up] - rec[:, self.lid_lo]) * normal.unsqueeze(2)).sum(-1)).mean(-1, keepdim=True)
        squash = torch.clamp(1.0 - self.eye_cap * width / gap, min=0.0)  # (B, 2, 1): 1 - cap / opening, or 0
        h = ((rec[:, self.eye_idx] - c0.unsqueeze(2)) * normal.unsqueeze(2)).sum(-1)  # (B, 2, n) across the corner line
        moved = ((squash * h).unsqueeze(-1) * normal.unsqueeze(2)).flatten(1, 2)  # (B, 2 n, 2)
        return rec - torch.matmul(self.put_eyes, moved)
