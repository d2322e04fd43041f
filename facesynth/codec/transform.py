"""H.264 4x4 integer core transform and QP quantisation, extended to 16-bit samples.

Forward ``W = Cf X Cf^T`` (Malvar et al. 2003), quantisation
``Z = sign(W) (|W| MF + f) >> (15 + QP // 6)`` and rescaling ``W' = Z V 2^(QP // 6)``
followed by the exact integer inverse butterfly and ``(x + 32) >> 6`` (ITU-T H.264
sec. 8.5.12). The step size doubles every 6 QP (``Qstep(0) = 0.625``); QP runs from 0 to
:data:`QP_MAX` so that steps reach the coarse end needed by 16-bit samples (all products
stay in int64). ``QP = None`` means lossless: the transform is bypassed and the residual
itself is coded.

Blocks are (..., N*N) raster rows; :func:`to_sub4` splits them into (..., N*N/16, 4, 4).
"""

from __future__ import annotations

import numpy as np

from facesynth.codec.blocks import sub_order, sub_perm
from facesynth.codec.transform8 import inverse_slots

QP_MAX = 87

_MF = np.array([[13107, 5243, 8066], [11916, 4660, 7490], [10082, 4194, 6554],
                [9362, 3647, 5825], [8192, 3355, 5243], [7282, 2893, 4559]], np.int64)
_V = np.array([[10, 16, 13], [11, 18, 14], [13, 20, 16], [14, 23, 18], [16, 25, 20], [18, 29, 23]], np.int64)
_POS = np.array([[0, 2, 0, 2], [2, 1, 2, 1], [0, 2, 0, 2], [2, 1, 2, 1]])  # a=0, b=1, c=2
CF = np.array([[1, 1, 1, 1], [2, 1, -1, -2], [1, -1, -1, 1], [1, -2, 2, -1]], np.int64)
ZIGZAG = np.array([0, 1, 4, 8, 5, 2, 3, 6, 9, 12, 13, 10, 7, 11, 14, 15])


def qstep(qp: int) -> float:
    """Quantiser step size of ``qp`` in sample units (0.625 at QP 0, x2 every 6)."""
    return (0.625, 0.6875, 0.8125, 0.875, 1.0, 1.125)[qp % 6] * 2.0 ** (qp // 6)


def lagrangian(qp: int | None) -> float:
    """H.264 reference lambda for SSD mode decisions: ``0.85 * 2^((QP - 12) / 3)``."""
    return 0.85 * 2.0 ** (((qp if qp is not None else 0) - 12) / 3.0)


def to_sub4(blocks: np.ndarray, n: int) -> np.ndarray:
    """(..., N*N) raster blocks -> (..., (N/4)^2, 4, 4) sub-blocks in raster order."""
    s = n // 4
    x = blocks.reshape(*blocks.shape[:-1], s, 4, s, 4)
    x = np.moveaxis(x, -3, -2)  # (..., s, s, 4, 4)
    return x.reshape(*blocks.shape[:-1], s * s, 4, 4)


def from_sub4(sub: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`to_sub4`."""
    s = n // 4
    x = sub.reshape(*sub.shape[:-3], s, s, 4, 4)
    x = np.moveaxis(x, -2, -3)
    return x.reshape(*sub.shape[:-3], n * n)


def _parts(x: np.ndarray, axis: int):
    return (x[..., i] for i in range(4)) if axis == -1 else (x[..., i, :] for i in range(4))


def _fwd_butterfly(x: np.ndarray, axis: int) -> np.ndarray:
    x0, x1, x2, x3 = _parts(x, axis)
    s0, s1, d0, d1 = x0 + x3, x1 + x2, x0 - x3, x1 - x2
    return np.stack([s0 + s1, 2 * d0 + d1, s0 - s1, d0 - 2 * d1], axis=axis)


def forward4(x: np.ndarray) -> np.ndarray:
    """Core transform of (..., 4, 4) int64 blocks: ``Cf X Cf^T`` (as butterflies)."""
    return _fwd_butterfly(_fwd_butterfly(x.astype(np.int64), -1), -2)


def _butterfly(d: np.ndarray, axis: int) -> np.ndarray:
    d0, d1, d2, d3 = _parts(d, axis)
    e0, e1 = d0 + d2, d0 - d2
    e2, e3 = (d1 >> 1) - d3, d1 + (d3 >> 1)
    return np.stack([e0 + e3, e1 + e2, e1 - e2, e0 - e3], axis=axis)


def inverse4(w: np.ndarray) -> np.ndarray:
    """Exact integer inverse of rescaled coefficients (..., 4, 4) -> residual, ``(x+32)>>6``."""
    x = _butterfly(_butterfly(w.astype(np.int64), -1), -2)
    return (x + 32) >> 6


def quantise(w: np.ndarray, qp: int, intra: bool = True) -> np.ndarray:
    """Quantise coefficients (..., 4, 4) to integer levels (dead zone 1/3 intra, 1/6 inter)."""
    qbits = 15 + qp // 6
    mf = _MF[qp % 6][_POS]
    f = (1 << qbits) // (3 if intra else 6)
    a = np.abs(w)
    return np.sign(w) * ((a * mf + f) >> qbits)


def dequantise(z: np.ndarray, qp: int) -> np.ndarray:
    """Rescale levels (..., 4, 4): ``Z V 2^(QP // 6)``."""
    return z * (_V[qp % 6][_POS] << (qp // 6))


def code_residual(res: np.ndarray, n: int, qp: int | None, intra: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Residual blocks (..., N*N) -> (levels (..., (N/4)^2, 16) in zigzag order,
    reconstructed residual (..., N*N)). ``qp=None`` is the lossless bypass."""
    sub = to_sub4(res, n)
    if qp is None:
        lev = sub
        rec = res
    else:
        lev = quantise(forward4(sub), qp, intra)
        rec = from_sub4(inverse4(dequantise(lev, qp)), n)
    return lev.reshape(*lev.shape[:-2], 16)[..., ZIGZAG], rec


_PF = np.array([0.25, 0.1, 0.1 ** 0.5 / 2])[_POS]  # orthonormal scale of each Cf coefficient
_M = np.array([4.0, 2.5, 2.5 ** 0.5 * 2])[_POS]  # orthonormal scale of each inverse basis (x 64)


def analyse_residual(res: np.ndarray, n: int, qp: int | None, intra: bool = True
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Levels (..., (N/4)^2, 16) zigzag and the SSD they will cause (...), without inverting.

    The core transform is orthogonal up to row scales, so by Parseval the pixel-domain
    error is ``sum((W * PF - Z * V 2^(QP//6) * M / 64)^2)`` (PF, M: the forward and
    inverse row scales); the integer inverse only adds its rounding. Lossless: SSD 0.
    """
    sub = to_sub4(res, n)
    if qp is None:
        return sub.reshape(*sub.shape[:-2], 16)[..., ZIGZAG], np.zeros(res.shape[:-1])
    w = forward4(sub)
    z = quantise(w, qp, intra)
    rm = (_V[qp % 6][_POS] << (qp // 6)) * _M / 64.0
    err = w * _PF - z * rm
    d = (err * err).reshape(*err.shape[:-3], -1).sum(-1)
    return z.reshape(*z.shape[:-2], 16)[..., ZIGZAG], d


def decode_residual(levels: np.ndarray, n: int, qp: int | None, as_float: bool = False,
                     t8: bool = False) -> np.ndarray:
    """Zigzag levels (..., (N/4)^2, 16) -> reconstructed residual (..., N*N), int64 (or
    float64 with the same integer values if ``as_float``). ``t8``: the levels are those of
    the 8x8 transform (:mod:`facesynth.codec.transform8`), N = 8 or 16."""
    if t8:
        z = levels[..., sub_order(n), :].reshape(*levels.shape[:-2], -1, 64)
        out = np.empty((*levels.shape[:-2], n * n), np.int64)
        out[..., sub_perm(n)] = inverse_slots(z, qp).reshape(*levels.shape[:-2], n * n)
        return out.astype(np.float64 if as_float else np.int64, copy=False)
    if qp is None:
        sub = np.empty_like(levels)
        sub[..., ZIGZAG] = levels
    else:  # the float matrix form of inverse4(dequantise(.)) (exact), for non-zero sub-blocks only
        flat = levels.reshape(-1, 16)
        nz = flat.any(1)
        sub = np.zeros(flat.shape)
        sub[nz] = inverse_sub(flat[nz].astype(np.float64), qp)
    out = from_sub4(sub.reshape(*levels.shape[:-1], 4, 4), n)
    return out.astype(np.float64 if as_float else np.int64, copy=False)


# --- the same transform as matrices on flattened 4x4 blocks, for the encoder: inputs in
# raster order, coefficients and levels in zigzag order

FWD16 = np.kron(CF, CF).T[:, ZIGZAG].astype(np.float64)  # x (..., 16) @ FWD16 = forward4, zigzag
MF_TABLE = _MF[:, _POS.ravel()[ZIGZAG]]  # (6, 16) quantiser multipliers per zigzag position
PF16 = _PF.ravel()[ZIGZAG]


def rescale_scale(qp: int) -> np.ndarray:
    """(16,) pixel-domain scale of one level per zigzag position (Parseval, see
    :func:`analyse_residual`)."""
    return ((_V[qp % 6][_POS] << (qp // 6)) * _M / 64.0).ravel()[ZIGZAG]


def _tap_pos(axis: int, line: int, t: int) -> int:
    """Raster index in a 4x4 block of tap ``t`` on ``line``: along the row (axis -1) or the column."""
    return 4 * line + t if axis == -1 else 4 * t + line


def _inverse_stage(axis: int) -> np.ndarray:
    """(32, 16) matrix of one inverse butterfly stage on ``[d, d >> 1]`` (flattened 4x4)."""
    a = np.zeros((32, 16))
    # out[0] = d0 + d2 + d1 + h3, out[1] = d0 - d2 + h1 - d3, out[2] = d0 - d2 - h1 + d3,
    # out[3] = d0 + d2 - d1 - h3 (the butterfly of :func:`inverse4`, h = d >> 1)
    taps = [[(0, 1), (2, 1), (1, 1), (19, 1)], [(0, 1), (2, -1), (17, 1), (3, -1)],
            [(0, 1), (2, -1), (17, -1), (3, 1)], [(0, 1), (2, 1), (1, -1), (19, -1)]]
    for line in range(4):
        for out in range(4):
            for src, wgt in taps[out]:
                half, k = divmod(src, 16)
                a[16 * half + _tap_pos(axis, line, k), _tap_pos(axis, line, out)] += wgt
    return a


_ZZ2 = np.concatenate([ZIGZAG, 16 + ZIGZAG])
_INV_ROWS_ZZ, _INV_COLS = _inverse_stage(-1)[_ZZ2], _inverse_stage(-2)


def inverse_sub(z: np.ndarray, qp: int) -> np.ndarray:
    """Signed levels (..., 16) in zigzag order (float) -> residual (..., 16) in raster order,
    the exact result of ``inverse4(dequantise(z))`` computed as two products in float64."""
    d = z * (_V[qp % 6][_POS] << (qp // 6)).ravel()[ZIGZAG]
    y = np.concatenate([d, np.floor(d * 0.5)], -1) @ _INV_ROWS_ZZ
    y = np.concatenate([y, np.floor(y * 0.5)], -1) @ _INV_COLS
    y += 32.0
    y *= 1.0 / 64
    return np.floor(y, out=y)
