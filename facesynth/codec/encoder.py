"""The frame encoder: wavefront prediction, transform-domain RD decisions, block-size choice.

For every wavefront (see :mod:`facesynth.codec.blocks`) the encoder forms all candidate
predictions of all its blocks and channels in one product, keeps the few of least
``SAD + sqrt(lambda) R_mode``, and keeps per block and channel the mode of least
``J = D + lambda(QP) (R_levels + R_mode)`` (D: the SSD the levels will cause, from the
transform domain by Parseval, times the block's mean mask weight; R_levels: an estimate
of the level bits, :func:`est_bits`; R_mode: ``-log2`` of the mode's running frequency in
its entropy-coding context, the channel and the mode above, so the choice follows what
the adaptive coder will charge). Levels are RD-quantised (RDOQ): each level is lowered
by one where that lowers ``D + lambda R`` of that level. Only the chosen candidate is
reconstructed, with the decoder's integer inverse.

Speed (the arithmetic is the decoder's, the layout is not):

- everything runs in float64 on integer values (exact: every sum stays below 2**53);
  prediction weights are pre-scaled by ``2**-SHIFT`` so ``floor(nb @ W + 1/2)`` is the
  decoder's ``(W nb + 2**(S-1)) >> S``;
- block samples are kept sub-block-major (:func:`~facesynth.codec.blocks.sub_perm`), so
  the 4x4 core transform of any block size is one product with a 16 x 16 matrix, and
  the source's coefficients are computed once per frame: a candidate's residual
  coefficients are ``F(x) - F(pred)``;
- channels are independent images, so independent frames (all-intra) are stacked along
  the channel axis and share the wavefront loop (:func:`encode_frames`).
"""

from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import numpy as np

from facesynth.codec import entropy, intra
from facesynth.codec import transform8 as t8m
from facesynth.codec.blocks import (
    MID,
    ModeSet,
    grid,
    motion_compensate,
    motion_search,
    padded,
    sad_maps,
    sub_order,
    sub_perm,
    unpadded,
)
from facesynth.codec.transform import (
    FWD16,
    MF_TABLE,
    PF16,
    ZIGZAG,
    inverse_sub,
    lagrangian,
    rescale_scale,
)

_C0, _C1, _CS = 2.0, 2.0, 1.0  # level rate model: C0 + C1 log2(1 + |l|) per non-zero, CS per sub-block
_DR_MAX = 64  # rate change of lowering a level l by one, tabulated up to l = 64 (larger: as 64)
_DR_TABLE = np.array([np.inf] + [_C1 * np.log2(v / (v + 1.0)) - _C0 * (v == 1) for v in range(1, _DR_MAX + 1)])


@lru_cache(maxsize=None)
def encoder_weights(n: int, pdp: bool, pvm: bool) -> np.ndarray:
    """(K, M * N*N) float64 prediction weights scaled by ``2**-SHIFT``, sub-block-major rows.

    Mode order is the :class:`~facesynth.codec.blocks.ModeSet` order: HIP (with an
    all-zero slot for Plane at 16x16, filled by :func:`~facesynth.codec.intra.plane16`),
    PDP, then PDP again for PVM (the map is added afterwards).
    """
    k, nn = intra.n_neighbours(n), n * n
    parts = [intra.hip_matrices(n)]
    if n == 16:
        parts.append(np.zeros((1, nn, k), np.int64))
    if pdp:
        parts.append(intra.pdp_matrices(n))
    if pvm:
        parts.append(intra.pdp_matrices(n))
    w = np.concatenate(parts, 0)[:, sub_perm(n), :]
    return np.ascontiguousarray(w.reshape(-1, k).T.astype(np.float64) * 2.0 ** -intra.SHIFT)


def est_bits(z: np.ndarray) -> np.ndarray:
    """Rough level bits of magnitudes (..., S, 16) -> (...): ``2 + 2 log2(1 + |l|)`` per
    non-zero level, 1 per 4x4 sub-block."""
    t = np.log2(z + 1.0)
    t += (_C0 / _C1) * np.minimum(z, 1.0)
    return _C1 * t.reshape(*z.shape[:-2], -1).sum(-1) + _CS * z.shape[-2]


def encode_frames(x: np.ndarray, prev: np.ndarray | None, cfg, weight: np.ndarray | None,
                  sizes_per_frame: list[tuple[int, ...]], channels: int, start: int | None = None):
    """Encode F frames stacked along the channel axis: x (F*C, H, W) int64.

    ``prev`` (C, H, W) makes it a P-frame (then F = 1). Each frame keeps, among its
    candidate sizes ``sizes_per_frame[f]``, the one of least total cost. With ``start``
    (usually the size chosen for the previous frame of the same type) the search is
    greedy: ``start`` first, then each neighbouring size outward for as long as the cost
    keeps falling (the cost is near unimodal in the block size); without it the search
    starts from the middle size. Frames with one or two candidate sizes try them all.
    Returns a list of (n, modes (C, nblk), levels (C, nblk, S, 16), mvs (C, nblk, 2),
    reconstruction (C, H, W)) per frame.
    """
    nf = len(sizes_per_frame)
    best: list = [None] * nf
    sads = sad_maps(x, prev, cfg.mv_range) if (prev is not None and cfg.inter) else None

    def run(n, fr):
        """Encode frames ``fr`` with size n; returns the frames whose best cost improved."""
        if not fr:
            return []
        rows = np.concatenate([np.arange(f * channels, (f + 1) * channels) for f in fr])
        modes, levels, mvs, rec, cost = encode_n(x[rows], prev, cfg, weight, n, sads, channels)
        better = []
        for i, f in enumerate(fr):
            sl = slice(i * channels, (i + 1) * channels)
            tot = float(cost[sl].sum())
            if best[f] is None or tot < best[f][0]:
                best[f] = (tot, (n, modes[sl], levels[sl], mvs[sl], rec[sl]))
                better.append(f)
        return better

    every = sorted(set().union(*sizes_per_frame))
    if start not in every:
        start = every[len(every) // 2]  # no previous choice: start in the middle
    greedy = [f for f in range(nf) if start in sizes_per_frame[f] and len(sizes_per_frame[f]) > 2]
    for n in sorted(set().union(*sizes_per_frame)):  # exhaustive for the other frames
        run(n, [f for f in range(nf) if f not in greedy and n in sizes_per_frame[f]])
    if greedy:
        run(start, greedy)
        for step in (-1, 1):
            alive = [f for f in greedy if best[f][1][0] == start]  # not improved the other way
            for n in (sorted(set().union(*sizes_per_frame)))[::step]:
                if (n - start) * step <= 0:
                    continue
                alive = run(n, [f for f in alive if n in sizes_per_frame[f]])
    return [b[1] for b in best]


def uses_t8(cfg, n: int) -> bool:
    """Whether N x N blocks of a frame coded with ``cfg`` use the 8x8 transform."""
    return bool(cfg.transform8) and n >= 8 and cfg.qp is not None


class _Quant:
    """Quantiser of one QP and dead zone (1/3 intra, 1/6 inter) with RDOQ and RD cost.

    4x4 transform: H.264's integer multipliers; 8x8 transform: the orthonormal step of
    :func:`~facesynth.codec.transform8.step` (the encoder's choice; only the decoder's
    rescaling is normative)."""

    def __init__(self, qp: int, lam: float, inter: bool, t8: bool = False):
        if t8:
            self.pf = t8m.PF64.reshape(4, 16)
            self.rm = t8m.step(qp).reshape(4, 16)
            self.mul = self.pf / self.rm
            self.f = 1.0 / 6 if inter else 1.0 / 3
        else:
            qbits = 15 + qp // 6
            self.mul = MF_TABLE[qp % 6] * 2.0 ** -qbits  # exact: a power-of-two scaling
            self.f = ((1 << qbits) // (6 if inter else 3)) * 2.0 ** -qbits
            self.pf = PF16
            self.rm = rescale_scale(qp)
        self.lam = lam
        self.lam_dr = lam * _DR_TABLE

    def __call__(self, coef: np.ndarray, wmb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients (..., S, 16) zigzag, block weights (...) -> (levels |z|, J = D wmb + lambda R).

        RDOQ: each level is lowered by one where that lowers ``D + lambda R`` of that level
        alone (R from :func:`est_bits`)."""
        a = np.abs(coef)
        shp = (*coef.shape[:-2], -1, *np.shape(self.rm)) if np.ndim(self.rm) == 2 else coef.shape
        a = a.reshape(shp)  # 8x8 transform: (..., S/4, 4, 16)
        z = a * self.mul
        z += self.f
        np.floor(z, out=z)
        err = a * self.pf
        err -= z * self.rm
        err2 = err * err
        err += self.rm
        delta = err * err  # D after lowering, then its change
        delta -= err2
        gain = delta * wmb.reshape(*wmb.shape, *([1] * (a.ndim - wmb.ndim)))
        gain += self.lam_dr[np.minimum(z, _DR_MAX).astype(np.intp)]
        down = gain < 0
        z -= down
        delta *= down
        err2 += delta
        z = z.reshape(coef.shape)
        d = err2.reshape(*coef.shape[:-2], -1).sum(-1)
        return z, d * wmb + self.lam * est_bits(z)


def encode_n(x: np.ndarray, prev: np.ndarray | None, cfg, weight: np.ndarray | None, n: int, sads=None,
             channels: int | None = None):
    """Encode (C, H, W) int64 with N x N blocks -> (modes, levels, mvs, reconstruction, cost (C,))."""
    c, h, w = x.shape
    f = _setup(x, prev, cfg, weight, n)
    inter = _inter_candidates(f, x, prev, cfg, sads) if f.ms.inter else None
    modes, zlev, cost, buf = _code_waves(f, channels or c, inter)
    if n == 16:
        zlev = zlev[:, :, np.argsort(sub_order(n))]  # sub-blocks back in raster order
    levels = zlev.astype(np.int64)
    mvs = np.zeros((c, f.g.n_blocks, 2), np.int64)
    if inter is not None:
        is_inter = modes[:, :-1] == f.mp
        mvs[is_inter] = inter.mvs[is_inter]
    o = f.o
    inv = np.empty_like(o)
    inv[o] = np.arange(len(o))  # back from wavefront order to raster block order
    rec = unpadded(buf, h, w).astype(np.int64)
    return modes[:, :-1][:, inv], levels[:, inv], mvs[:, inv], rec, cost


def _transforms(t8: bool, qp, s_sub: int, nn: int):
    """(forward, inverse): samples (..., NN) -> coefficients (..., S, 16) and signed levels
    (..., S, 16) -> residual (..., NN), in the encoder's sub-block-major sample order."""
    if t8:
        def fwd(v):  # 8x8 blocks, 4 slots each
            return (v.reshape(-1, 64) @ t8m.FWD64).reshape(*v.shape[:-1], s_sub, 16)

        def inv(zc):
            return t8m.inverse_slots_float(zc.reshape(*zc.shape[:-2], -1, 64), qp).reshape(*zc.shape[:-2], nn)
    else:
        def fwd(v):
            return (v.reshape(-1, 16) @ FWD16).reshape(*v.shape[:-1], s_sub, 16)

        def inv(zc):
            return inverse_sub(zc, qp).reshape(*zc.shape[:-2], nn)
    return fwd, inv


def _setup(x: np.ndarray, prev: np.ndarray | None, cfg, weight: np.ndarray | None, n: int) -> SimpleNamespace:
    """What every wavefront of one block size reads: block layout (wavefront order), mode
    set, lambda, prediction weights, the source's samples and coefficients, the transforms,
    the quantiser and the pixel-varying maps."""
    c, h, w = x.shape
    g = grid(n, h, w)
    p_frame = prev is not None
    ms = ModeSet(n, cfg.pdp, cfg.pvm and p_frame, cfg.inter and p_frame)
    qp = cfg.qp
    lam = lagrangian(qp) * cfg.lambda_scale
    perm = sub_perm(n)
    nn, s_sub = n * n, (n // 4) ** 2
    o = g.order  # wavefront order: each wave is a contiguous slice
    pix_r = g.pix_idx[o]  # raster order (inter, mask)
    pix = pix_r[:, perm]  # sub-block-major order
    nbo = g.nb_idx[o]
    xpad = padded(x)
    xs = xpad[:, pix].astype(np.float64)  # (C, nblk, NN)
    wt = np.ones((h, w)) if weight is None else np.where(weight, 1.0, cfg.outside_weight)
    wm = np.pad(wt, ((1, 0), (1, 0))).ravel()[pix_r].mean(-1)
    mp = ms.n_predictive
    t8 = uses_t8(cfg, n)
    fwd, inv = _transforms(t8, qp, s_sub, nn)
    lossless = qp is None
    maps = None
    if ms.pvm:  # the previous frame's pixel-varying maps prev - PDP_d(prev neighbours): (C, nblk, 4, NN)
        pp = padded(prev).astype(np.float64)
        nbp = pp[:, nbo]
        maps = np.floor((nbp.reshape(-1, nbp.shape[-1]) @ encoder_weights(n, True, False)[:, -4 * nn:]) + 0.5)
        maps = pp[:, pix][:, :, None, :] - maps.reshape(c, -1, 4, nn)
    return SimpleNamespace(
        n=n, c=c, g=g, ms=ms, qp=qp, lam=lam, perm=perm, nn=nn, s_sub=s_sub, o=o, pix=pix, nbo=nbo, xpad=xpad,
        xs=xs, wm=wm, wmat=encoder_weights(n, ms.pdp, ms.pvm), f8=intra.filter8_matrix() * 0.25 if n == 8 else None,
        mp=mp, kk=mp if not cfg.rd_candidates else min(cfg.rd_candidates, mp), lossless=lossless, t8=t8,
        fwd=fwd, inv=inv, fx=None if lossless else fwd(xs), quant=None if lossless else _Quant(qp, lam, inter=False, t8=t8),
        maps=maps)


def _inter_candidates(f: SimpleNamespace, x: np.ndarray, prev: np.ndarray, cfg, sads) -> SimpleNamespace:
    """The motion-compensated candidate of every block at once (wavefront order): motion
    vectors, RD cost, signed levels and reconstruction."""
    mvs_r = motion_search(x, prev, f.n, cfg.mv_range, sads)
    mvs = mvs_r[:, f.o]
    pi = motion_compensate(prev, mvs_r, f.n, cfg.mv_range)[:, f.o][..., f.perm].astype(np.float64)
    mvbits = 2.0 * (np.abs(mvs) > 0).sum(-1) + 1.0
    if f.lossless:
        zc = (f.xs - pi).reshape(f.c, -1, f.s_sub, 16)[..., ZIGZAG]
        j = f.lam * (est_bits(np.abs(zc)) + mvbits)
        rec = f.xs
    else:
        coef = f.fx - f.fwd(pi)
        z, j = _Quant(f.qp, f.lam, inter=True, t8=f.t8)(coef, f.wm[None])
        j += f.lam * mvbits
        zc = np.copysign(z, coef)
        rec = np.clip(pi + f.inv(zc), 0, 65535)
    return SimpleNamespace(mvs=mvs, j=j, zc=zc, rec=rec)


def _predict(f: SimpleNamespace, nb: np.ndarray, s: int, e: int) -> np.ndarray:
    """Every predictive mode's (scaled, unrounded) prediction of the blocks s:e from their
    neighbour samples nb (C, b, K): (C, b, modes, NN)."""
    c, b, n, nn, mp = f.c, e - s, f.n, f.nn, f.mp
    if n == 8:  # HIP 8x8 modes predict from the filtered samples (exact: floor of quarters)
        nbf = np.floor(nb.reshape(-1, nb.shape[-1]) @ f.f8 + 0.5)
        pred = np.concatenate([nbf @ f.wmat[:, :9 * nn], nb.reshape(-1, nb.shape[-1]) @ f.wmat[:, 9 * nn:]], 1)
        pred = pred.reshape(c, b, mp, nn)
    else:
        pred = (nb.reshape(-1, nb.shape[-1]) @ f.wmat).reshape(c, b, mp, nn)
    if n == 16:
        pred[:, :, 3] = intra.plane16(nb.astype(np.int64))[..., f.perm]
    if f.ms.pvm:
        pred[:, :, f.ms.n_spatial:] += f.maps[:, s:e]
    return pred


def _prune(f: SimpleNamespace, pred: np.ndarray, xw: np.ndarray, mbits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The kk modes of least SAD + sqrt(lambda) mode bits (the H.264 reference encoder's
    pre-selection) before the full RD test: (their predictions (C, b, kk, NN), their modes)."""
    c, b, kk, mp, nn = pred.shape[0], pred.shape[1], f.kk, f.mp, f.nn
    if kk >= mp:
        return pred, np.broadcast_to(np.arange(mp), (c, b, mp))
    d = pred - xw[:, :, None]
    np.abs(d, out=d)
    sad = (d.reshape(-1, nn) @ np.ones(nn)).reshape(c, b, mp)
    sad += np.sqrt(f.lam) * mbits[..., :mp]
    cand = np.argpartition(sad, kk - 1, axis=-1)[..., :kk]
    rows = (np.arange(c * b).reshape(c, b, 1) * mp + cand).ravel()
    return pred.reshape(-1, nn)[rows].reshape(c, b, kk, nn), cand


def _code_waves(f: SimpleNamespace, channels: int, inter: SimpleNamespace | None):
    """Code the blocks wave by wave, each block and channel with its mode of least RD cost:
    (modes (C, nblk + 1) in wave order, zigzag levels (C, nblk, S, 16), cost (C,), the
    padded reconstruction)."""
    c, g, nm, mp, kk, lam = f.c, f.g, f.ms.n_modes, f.mp, f.kk, f.lam
    modes = np.full((c, g.n_blocks + 1), nm, np.int64)  # wave order; the last column: "no block above"
    pos = np.empty_like(f.o)
    pos[f.o] = np.arange(len(f.o))
    nbx = g.shape[1]
    above = np.where(f.o >= nbx, pos[np.maximum(f.o - nbx, 0)], g.n_blocks)  # wave position of the block above
    chan = (np.arange(c) % channels)[:, None]
    mcnt = np.ones((c, entropy.n_mode_contexts(channels, nm), nm))  # running mode statistics per context
    zlev = np.zeros((c, g.n_blocks, f.s_sub, 16))  # levels, zigzag order
    cost = np.zeros(c)
    buf = np.full(f.xpad.shape, float(MID))
    cidx = np.arange(c)[:, None]
    for s, e in g.bounds:
        b = e - s
        xw = f.xs[:, s:e]
        bidx = np.arange(b)[None, :]
        ctx = entropy.mode_ctx(modes[:, above[s:e]], chan, nm)
        cnt = mcnt[cidx, ctx]  # (C, b, nm)
        mbits = np.log2(cnt.sum(-1, keepdims=True)) - np.log2(cnt)  # adaptive mode cost estimate
        pred, cand = _prune(f, _predict(f, buf[:, f.nbo[s:e]], s, e), xw, mbits)
        # the decoder's rounding and clipping, for the candidates only (Plane is integer already)
        pred += 0.5
        np.floor(pred, out=pred)
        np.clip(pred, 0, 65535, out=pred)
        if f.lossless:
            coef = (xw[:, :, None] - pred).reshape(c, b, kk, f.s_sub, 16)[..., ZIGZAG]
            z = np.abs(coef)
            j = lam * est_bits(z)
        else:
            coef = f.fx[:, s:e, None] - f.fwd(pred)
            z, j = f.quant(coef, f.wm[None, s:e, None])
        j += lam * mbits.reshape(-1)[(np.arange(c * b).reshape(c, b, 1) * nm + cand)]
        if inter is not None:
            j = np.concatenate([j, (inter.j[:, s:e] + lam * mbits[..., mp])[..., None]], -1)
        bl = np.argmin(j, -1)
        bi = np.minimum(bl, kk - 1)
        zc = np.copysign(z[cidx, bidx, bi], coef[cidx, bidx, bi])  # (C, b, S, 16) signed levels
        if f.lossless:
            r = xw  # the residual is coded as is
        else:
            x_rec = pred[cidx, bidx, bi] + f.inv(zc)
            r = np.clip(x_rec, 0, 65535, out=x_rec)
        if inter is not None:
            is_i = bl == kk
            r = np.where(is_i[..., None], inter.rec[:, s:e], r)
            zc = np.where(is_i[..., None, None], inter.zc[:, s:e], zc)
            modes[:, s:e] = np.where(is_i, mp, cand[cidx, bidx, bi])
        else:
            modes[:, s:e] = cand[cidx, bidx, bi]
        np.add.at(mcnt, (np.broadcast_to(cidx, (c, b)), ctx, modes[:, s:e]), 4.0)
        buf[:, f.pix[s:e]] = r
        zlev[:, s:e] = zc
        cost += j[cidx, bidx, bl].sum(1)
    return modes, zlev, cost, buf
