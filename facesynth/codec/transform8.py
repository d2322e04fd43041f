"""The H.264 High-profile 8x8 integer transform, for 8x8 and 16x16 blocks.

Inverse: the butterfly of ITU-T H.264 sec. 8.5.13.2 (rows, then columns), equal to
``T^T D T / 64`` up to its internal ``>> 1`` / ``>> 2`` roundings, with the integer basis
``T`` (:data:`T8`, orthogonal rows of squared norms 512, 578, 320, 578, 512, 578, 320, 578).
Dequantisation ``D = Z * A(QP % 6, class) << (QP // 6)`` uses the standard's normAdjust8
table ``A`` with a flat weighting matrix, kept exact (the standard divides by 4 with
rounding first), so the final rounding is ``(x + 128) >> 8``; the step of every
coefficient then matches the 4x4 path's ``Qstep(QP)`` within 3 %.

Layout: the 64 coefficients of an 8x8 block in zigzag order are dealt round-robin into
four 16-coefficient slots (coefficient ``k`` -> slot ``k % 4``, position ``k // 4``, as
H.264's CAVLC does), the slots of the four 4x4 sub-blocks of that 8x8 block, so the
level arrays, the entropy coder and its contexts are those of the 4x4 path. Samples of an
8x8 block are taken sub-block-major (four 4x4 sub-blocks in raster order, each in raster
order), see :func:`~facesynth.codec.blocks.sub_perm`.
"""

from __future__ import annotations

import numpy as np

T8 = np.array([[8, 8, 8, 8, 8, 8, 8, 8], [12, 10, 6, 3, -3, -6, -10, -12], [8, 4, -4, -8, -8, -4, 4, 8],
               [10, -3, -12, -6, 6, 12, 3, -10], [8, -8, -8, 8, 8, -8, -8, 8], [6, -12, 3, 10, -10, -3, 12, -6],
               [4, -8, 8, -4, -4, 8, -8, 4], [3, -6, 10, -12, 12, -10, 6, -3]], np.int64)
_NORM = np.sqrt((T8 * T8).sum(1).astype(np.float64))  # row norms
_ADJ = np.array([[20, 18, 32, 19, 25, 24], [22, 19, 35, 21, 28, 26], [26, 23, 42, 24, 33, 31],
                 [28, 25, 45, 26, 35, 33], [32, 28, 51, 30, 40, 38], [36, 32, 58, 34, 46, 43]], np.int64)


def _zigzag8() -> np.ndarray:
    """(64,) raster index (8 u + v) of each zigzag position (frame scan)."""
    out = []
    for s in range(15):
        rows = range(max(0, s - 7), min(s, 7) + 1)
        rows = rows if s % 2 else reversed(rows)
        out += [8 * r + (s - r) for r in rows]
    return np.array(out)


ZIGZAG8 = _zigzag8()


def _pos_class(u: int, v: int) -> int:
    """Position class of coefficient (u, v) in the normAdjust8 table (sec. 8.5.9)."""
    if u % 4 == 0 and v % 4 == 0:
        return 0
    if u % 2 == 1 and v % 2 == 1:
        return 1
    if u % 4 == 2 and v % 4 == 2:
        return 2
    if (u % 4 == 0 and v % 2 == 1) or (u % 2 == 1 and v % 4 == 0):
        return 3
    if (u % 4 == 0 and v % 4 == 2) or (u % 4 == 2 and v % 4 == 0):
        return 4
    return 5


# slot order i (0..63: slot i // 16, position i % 16) -> zigzag index and (u, v)
_SLOT_ZZ = (np.arange(64) % 16) * 4 + np.arange(64) // 16
SLOT_UV = np.stack(np.divmod(ZIGZAG8[_SLOT_ZZ], 8), 1)  # (64, 2)
_CLASS = np.array([_pos_class(u, v) for u, v in SLOT_UV])
# sample j of an 8x8 block in sub-block-major order -> (y, x)
_a, _r = np.divmod(np.arange(64), 16)
SAMPLE_YX = np.stack([(_a // 2) * 4 + _r // 4, (_a % 2) * 4 + _r % 4], 1)

# forward: coefficients (slot order) = samples (sub-block-major) @ FWD64, W = T X T^T
FWD64 = (T8[SLOT_UV[:, 0]][:, SAMPLE_YX[:, 0]] * T8[SLOT_UV[:, 1]][:, SAMPLE_YX[:, 1]]).T.astype(np.float64)
PF64 = 1.0 / (_NORM[SLOT_UV[:, 0]] * _NORM[SLOT_UV[:, 1]])  # orthonormal scale of each coefficient


def dequant_scale(qp: int) -> np.ndarray:
    """(64,) integer dequantisation factor per slot-order coefficient: ``A << (QP // 6)``."""
    return _ADJ[qp % 6][_CLASS] << (qp // 6)


def step(qp: int) -> np.ndarray:
    """(64,) quantiser step per coefficient in orthonormal units (reconstruction
    ``T^T (Z A 2^(QP//6)) T / 2^14``)."""
    return dequant_scale(qp) / (PF64 * 16384.0)


def _rows(d: np.ndarray, axis: int) -> np.ndarray:
    """One 1-D pass of the sec. 8.5.13.2 butterfly along ``axis`` (-1 rows, -2 columns)."""
    d0, d1, d2, d3, d4, d5, d6, d7 = (d[..., i] if axis == -1 else d[..., i, :] for i in range(8))
    e0, e2 = d0 + d4, d0 - d4
    e1 = -d3 + d5 - d7 - (d7 >> 1)
    e3 = d1 + d7 - d3 - (d3 >> 1)
    e4 = (d2 >> 1) - d6
    e5 = -d1 + d7 + d5 + (d5 >> 1)
    e6 = d2 + (d6 >> 1)
    e7 = d3 + d5 + d1 + (d1 >> 1)
    f0, f6 = e0 + e6, e0 - e6
    f1 = e1 + (e7 >> 2)
    f2, f4 = e2 + e4, e2 - e4
    f3 = e3 + (e5 >> 2)
    f5 = (e3 >> 2) - e5
    f7 = e7 - (e1 >> 2)
    return np.stack([f0 + f7, f2 + f5, f4 + f3, f6 + f1, f6 - f1, f4 - f3, f2 - f5, f0 - f7], axis=axis)


def inverse8(d: np.ndarray) -> np.ndarray:
    """Dequantised coefficients (..., 8, 8) (row u, column v) int64 -> residual (..., 8, 8):
    the butterfly on rows, then on columns, then ``(x + 128) >> 8``."""
    return (_rows(_rows(d.astype(np.int64), -1), -2) + 128) >> 8


def inverse_slots(z: np.ndarray, qp: int) -> np.ndarray:
    """Signed levels (..., 64) in slot order -> residual (..., 64) in sub-block-major
    sample order, int64."""
    d = np.zeros((*z.shape[:-1], 64), np.int64)
    d[..., SLOT_UV[:, 0] * 8 + SLOT_UV[:, 1]] = z.astype(np.int64) * dequant_scale(qp)
    x = inverse8(d.reshape(*z.shape[:-1], 8, 8)).reshape(*z.shape[:-1], 64)
    return x[..., SAMPLE_YX[:, 0] * 8 + SAMPLE_YX[:, 1]]


def _stage_matrices() -> tuple[np.ndarray, np.ndarray]:
    """The 1-D butterfly of :func:`_rows` as two linear maps on 8-vectors:
    ``e = [d, d >> 1] @ E`` and ``out = [e, e >> 2] @ G`` (both 16 x 8)."""
    E = np.zeros((16, 8))
    G = np.zeros((16, 8))
    d, h = (lambda k: k), (lambda k: 8 + k)  # indices of d[k] and d[k] >> 1 (or e[k], e[k] >> 2)
    e_taps = [[(d(0), 1), (d(4), 1)], [(d(3), -1), (d(5), 1), (d(7), -1), (h(7), -1)],
              [(d(0), 1), (d(4), -1)], [(d(1), 1), (d(7), 1), (d(3), -1), (h(3), -1)],
              [(h(2), 1), (d(6), -1)], [(d(1), -1), (d(7), 1), (d(5), 1), (h(5), 1)],
              [(d(2), 1), (h(6), 1)], [(d(3), 1), (d(5), 1), (d(1), 1), (h(1), 1)]]
    for k, taps in enumerate(e_taps):
        for i, wgt in taps:
            E[i, k] += wgt
    f = [[(d(0), 1), (d(6), 1)], [(d(1), 1), (h(7), 1)], [(d(2), 1), (d(4), 1)], [(d(3), 1), (h(5), 1)],
         [(d(2), 1), (d(4), -1)], [(h(3), 1), (d(5), -1)], [(d(0), 1), (d(6), -1)], [(d(7), 1), (h(1), -1)]]
    g = [(0, 7, 1), (2, 5, 1), (4, 3, 1), (6, 1, 1), (6, 1, -1), (4, 3, -1), (2, 5, -1), (0, 7, -1)]
    for k, (i, j, sgn) in enumerate(g):
        for src, wgt in f[i]:
            G[src, k] += wgt
        for src, wgt in f[j]:
            G[src, k] += sgn * wgt
    return E, G


_E8, _G8 = _stage_matrices()
_SLOT_RASTER = SLOT_UV[:, 0] * 8 + SLOT_UV[:, 1]
_SAMPLE_RASTER = SAMPLE_YX[:, 0] * 8 + SAMPLE_YX[:, 1]


def _pass_float(d: np.ndarray) -> np.ndarray:
    """One 1-D butterfly pass along the last axis of (..., 8) float rows (exact)."""
    e = np.concatenate([d, np.floor(d * 0.5)], -1) @ _E8
    return np.concatenate([e, np.floor(e * 0.25)], -1) @ _G8


def inverse_slots_float(z: np.ndarray, qp: int) -> np.ndarray:
    """:func:`inverse_slots` in float64 (exact: integers below 2**53, floors of exact
    halves and quarters): signed levels (..., 64) slot order -> residual (..., 64)."""
    flat = z.reshape(-1, 64)
    nz = flat.any(1)  # all-zero blocks stay zero: transform only the others
    out = np.zeros(flat.shape)
    if nz.any():
        out[nz] = _inverse_rows(flat[nz], qp)
    return out.reshape(*z.shape[:-1], 64)


def _inverse_rows(z: np.ndarray, qp: int) -> np.ndarray:
    x = z * dequant_scale(qp)
    d = np.empty_like(x)
    d[:, _SLOT_RASTER] = x
    d = _pass_float(d.reshape(-1, 8))  # rows
    d = _pass_float(d.reshape(-1, 8, 8).swapaxes(1, 2).reshape(-1, 8))  # columns
    d = d.reshape(-1, 8, 8).swapaxes(1, 2).reshape(-1, 64)
    d += 128.0
    d *= 1.0 / 256
    np.floor(d, out=d)
    return d[:, _SAMPLE_RASTER]
