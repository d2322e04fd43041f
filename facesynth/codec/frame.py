"""Frame-level API: encoder settings, frame codes, the decoder and frame serialisation.

The encoder itself lives in :mod:`facesynth.codec.encoder` (wavefront prediction,
transform-domain RD decisions, per-frame block-size choice). The decoder entropy-decodes
the whole frame first, rebuilds all residuals in one pass, then runs the wavefront with
the chosen modes only; its arithmetic (exact float64 sums of integers, floor, clips) is
the encoder's, so its output equals the encoder's reconstruction bit for bit.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from facesynth.codec import encoder, entropy, intra
from facesynth.codec.blocks import MID, ModeSet, grid, motion_compensate, padded, unpadded
from facesynth.codec.intra import n_neighbours
from facesynth.codec.transform import decode_residual


@dataclass
class CodecConfig:
    """Encoder settings.

    qp : int or None (lossless); pdp : spatial PDP modes; pvm : temporal PDP (PVM) modes
    in P-frames; inter : motion-compensated prediction in P-frames; gop : frames per
    group (1 = all intra); block_sizes : candidate N per frame (None: 8 and 16 with the 8x8
    transform, where 4x4 blocks were never chosen on the ICT video, else 4, 8, 16, see
    :meth:`sizes`); mv_range : full-search
    range in pixels; outside_weight : weight of pixels outside the mask in D;
    rd_candidates : full RD test only for this many modes of least SAD (0 = all);
    lambda_scale : multiplies the H.264 lambda(QP); size_refresh : all block sizes are
    tried on I-frames and every ``size_refresh``-th frame, the others reuse the last
    choice within the same frame type (0 or 1 = try all sizes on every frame);
    batch_frames : all-intra streams (gop 1) encode this many frames at once (the frames
    are independent; the bitstream does not depend on it); transform8 : 8x8 and 16x16
    blocks use the 8x8 integer transform (:mod:`facesynth.codec.transform8`).
    """

    qp: int | None = 30
    pdp: bool = True
    pvm: bool = True
    inter: bool = True
    gop: int = 1
    block_sizes: tuple[int, ...] | None = None
    mv_range: int = 2
    outside_weight: float = 0.05
    rd_candidates: int = 3
    lambda_scale: float = 0.7  # on the H.264 lambda; measured optimum with the 8x8 transform
    size_refresh: int = 4
    batch_frames: int = 8
    transform8: bool = True


    def sizes(self) -> tuple[int, ...]:
        """The candidate block sizes in effect."""
        if self.block_sizes is not None:
            return tuple(self.block_sizes)
        return (8, 16) if (self.transform8 and self.qp is not None) else (4, 8, 16)


@dataclass
class FrameCode:
    n: int
    p_frame: bool
    modes: np.ndarray  # (C, nblk)
    levels: np.ndarray  # (C, nblk, (N/4)^2, 16)
    mvs: np.ndarray  # (C, nblk, 2)
    stats: dict = field(default_factory=dict)
    t8: bool = False  # residuals through the 8x8 transform


def mode_set(cfg_pdp: bool, cfg_pvm: bool, cfg_inter: bool, n: int, p_frame: bool) -> ModeSet:
    return ModeSet(n, cfg_pdp, cfg_pvm and p_frame, cfg_inter and p_frame)


def encode_frame(x: np.ndarray, prev: np.ndarray | None, cfg: CodecConfig,
                 weight: np.ndarray | None = None, sizes: tuple[int, ...] | None = None,
                 start: int | None = None) -> tuple[FrameCode, np.ndarray]:
    """Encode one frame (C, H, W) int64; ``prev`` (C, H, W) makes it a P-frame.

    ``sizes`` overrides ``cfg.sizes()`` (the candidate block sizes tried); ``start``
    makes the size search greedy from that size (:func:`encoder.encode_frames`).
    Returns the frame's code and its reconstruction (C, H, W) int64.
    """
    return encode_batch(x[None], prev, cfg, weight, [tuple(sizes or cfg.sizes())], start)[0]


def encode_batch(xs: np.ndarray, prev: np.ndarray | None, cfg: CodecConfig, weight: np.ndarray | None,
                 sizes_per_frame: list[tuple[int, ...]], start: int | None = None
                 ) -> list[tuple[FrameCode, np.ndarray]]:
    """Encode F independent frames xs (F, C, H, W) at once (F = 1 for a P-frame)."""
    f, c = xs.shape[:2]
    out = encoder.encode_frames(xs.reshape(f * c, *xs.shape[2:]), prev, cfg, weight, sizes_per_frame, c, start)
    return [(FrameCode(n, prev is not None, modes, levels, mvs, t8=encoder.uses_t8(cfg, n)), rec)
            for n, modes, levels, mvs, rec in out]


def decode_frame(code: FrameCode, prev: np.ndarray | None, qp: int | None, flags: tuple[bool, bool, bool],
                 mv_range: int, shape: tuple[int, int, int]) -> np.ndarray:
    """Reconstruct one frame (C, H, W) int64 from its code.

    Each block's mode is turned into one row of a weight bank (HIP, PDP, or zeros for
    inter) plus an additive term (PVM map or motion-compensated block), so a wavefront
    step is one batched product for the chosen modes only. The arithmetic (float64 sums
    of integers, exact; floor; clips) is the encoder's, so the output is bit-exact.
    """
    c, h, w = shape
    n = code.n
    g = grid(n, h, w)
    ms = mode_set(*flags, n, code.p_frame)
    nh = 3 if n == 16 else 9
    bank = np.concatenate([intra.hip_matrices(n), intra.pdp_matrices(n),
                           np.zeros((1, n * n, n_neighbours(n)), np.int64)], 0)
    bank = np.ascontiguousarray(np.swapaxes(bank, 1, 2).astype(np.float64))  # (modes, K, N*N)
    modes = code.modes
    lin = modes.copy()
    plane = np.zeros_like(modes, bool)
    add = np.zeros((c, g.n_blocks, n * n))
    if n == 16:
        plane = modes == 3
        lin = np.where(modes > 3, modes - 1, np.where(plane, 0, modes))
    first_pvm = ms.n_spatial
    if ms.pvm:  # maps only for the blocks that use PVM
        is_pvm = (modes >= first_pvm) & (modes < first_pvm + 4)
        d = np.clip(modes - first_pvm, 0, 3)
        ci, bi = np.nonzero(is_pvm)
        pb = padded(prev)
        maps = intra.pvm_maps(pb[ci[:, None], g.pix_idx[bi]], pb[ci[:, None], g.nb_idx[bi]], n)
        add[ci, bi] = maps[np.arange(len(ci)), d[ci, bi]]
        lin = np.where(is_pvm, nh + d, lin)
    if ms.inter:
        is_i = modes == ms.inter_mode
        pi = motion_compensate(prev, code.mvs, n, mv_range)
        add[is_i] = pi[is_i]
        lin = np.where(is_i, nh + 4, lin)
    o = g.order  # everything in wavefront order: each wave is a contiguous slice
    res = decode_residual(code.levels[:, o], n, qp, as_float=True, t8=code.t8)
    add, lin, plane = add[:, o], lin[:, o], plane[:, o]
    nb_idx, pix_idx = g.nb_idx[o], g.pix_idx[o]
    buf = padded(np.full(shape, MID, np.int64)).astype(np.float64)
    any_plane = plane.any()
    half, scale = 2.0 ** (intra.SHIFT - 1), 2.0 ** -intra.SHIFT
    f8 = intra.filter8_matrix() * 0.25 if n == 8 else None
    for s, e in g.bounds:
        nbv = buf[:, nb_idx[s:e]]
        if n == 8:  # HIP 8x8 modes (bank rows 0..8) predict from the filtered samples
            nbv = np.where((lin[:, s:e] < 9)[..., None], np.floor(nbv @ f8 + 0.5), nbv)
        acc = np.matmul(nbv[:, :, None, :], bank[lin[:, s:e]])[:, :, 0]
        acc += half
        acc *= scale
        np.floor(acc, out=acc)
        acc += add[:, s:e]
        if any_plane:
            sel = plane[:, s:e]
            if sel.any():
                acc[sel] = intra.plane16(nbv[sel].astype(np.int64))
        np.clip(acc, 0, 65535, out=acc)
        acc += res[:, s:e]
        np.clip(acc, 0, 65535, out=acc)
        buf[:, pix_idx[s:e]] = acc
    return unpadded(buf, h, w).astype(np.int64)


def to_sub_grid(levels: np.ndarray, g) -> np.ndarray:
    """Levels (C, nblk, S, 16) -> (C * H/4 * W/4, 16): 4x4 sub-blocks in raster order over the frame."""
    c, s = levels.shape[0], g.n // 4
    by, bx = g.shape
    x = levels.reshape(c, by, bx, s, s, 16).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(-1, 16)


def from_sub_grid(rows: np.ndarray, g) -> np.ndarray:
    """Inverse of :func:`to_sub_grid` -> (C, nblk, S, 16)."""
    s = g.n // 4
    by, bx = g.shape
    x = rows.reshape(-1, by, s, bx, s, 16).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(x.shape[0], by * bx, s * s, 16)


_FRAME_HDR = struct.Struct("<BBB")


def write_frame(code: FrameCode, flags: tuple[bool, bool, bool], mv_range: int, shape) -> bytes:
    """Serialise a frame's symbols: 3-byte header + range-coder words."""
    c, h, w = shape
    ms = mode_set(*flags, code.n, code.p_frame)
    g = grid(code.n, h, w)
    enc = entropy.RangeEncoder()
    entropy.encode_modes(enc, code.modes.reshape(c, *g.shape), ms.n_modes)
    if ms.inter:
        entropy.encode_mvs(enc, code.mvs[code.modes == ms.inter_mode], mv_range)
    entropy.encode_levels(enc, to_sub_grid(code.levels, g), (c, h // 4, w // 4))
    words = enc.get_compressed()
    return _FRAME_HDR.pack(int(code.p_frame), code.n | (128 * code.t8), mv_range) + words.astype("<u4").tobytes()


def read_frame(payload: bytes, flags: tuple[bool, bool, bool], shape, lossless: bool = False
               ) -> tuple[FrameCode, int]:
    """Parse :func:`write_frame` output -> (FrameCode, mv_range). Raises ValueError if malformed."""
    c, h, w = shape
    if len(payload) < _FRAME_HDR.size or (len(payload) - _FRAME_HDR.size) % 4:
        raise ValueError("frame payload has a bad length")
    p, n, mv_range = _FRAME_HDR.unpack_from(payload)
    t8, n = bool(n & 128), n & 127
    if p not in (0, 1) or n not in (4, 8, 16) or h % n or w % n or (t8 and (n == 4 or lossless)):
        raise ValueError(f"bad frame header (type {p}, block size {n}, 8x8 transform {t8})")
    ms = mode_set(*flags, n, bool(p))
    g = grid(n, h, w)
    words = np.frombuffer(payload, "<u4", offset=_FRAME_HDR.size).astype(np.uint32)
    dec = entropy.RangeDecoder(words)
    modes = entropy.decode_modes(dec, (c, *g.shape), ms.n_modes).reshape(c, -1)
    mvs = np.zeros((c, g.n_blocks, 2), np.int64)
    if ms.inter:
        sel = modes == ms.inter_mode
        mvs[sel] = entropy.decode_mvs(dec, int(sel.sum()), mv_range)
    nsub = (n // 4) ** 2
    levels = from_sub_grid(entropy.decode_levels(dec, c * g.n_blocks * nsub, (c, h // 4, w // 4)), g)
    return FrameCode(n, bool(p), modes, levels, mvs, t8=t8), mv_range
