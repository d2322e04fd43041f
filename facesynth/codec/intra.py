"""Intra prediction as matrix products over neighbour vectors.

Every block of size N has one neighbour vector of ``K = 3N + 1`` reconstructed samples:
``nb[0] = M`` (top-left corner), ``nb[1:2N+1] = T[0..2N-1]`` (the row above, including
the N samples above-right), ``nb[2N+1:] = L[0..N-1]`` (the column to the left). A mode
is an integer matrix ``W`` (N*N, K) with ``pred = (W @ nb + 2**(S-1)) >> S`` (``S = 12``),
so all modes of all blocks in a wavefront are one matrix product; predictions are clipped
to [0, 65535].

Modes (index: name):

- HIP, N = 4 and 8: the nine H.264 intra 4x4 / 8x8 modes (ITU-T H.264 sec. 8.3.1.2 and
  8.3.2.2; at 8x8 the matrices apply to the low-pass filtered reference samples of
  sec. 8.3.2.2.1, :func:`filter8`) 0 V, 1 H, 2 DC, 3 DDL, 4 DDR, 5 VR, 6 HD, 7 VL, 8 HU.
- HIP, N = 16: the four H.264 intra 16x16 modes 0 V, 1 H, 2 DC, 3 Plane (sec. 8.3.3).
  Plane has nested rounding, so it is computed directly (:func:`plane16`), not as a matrix.
- PDP (after Xia et al., progressive directional prediction): H, V, DDL, DDR with a
  trend from the boundary, ``gx = (T[N-1] - M) / N``, ``gy = (L[N-1] - M) / N``. Along
  the direction, each pixel lies on a line that starts at a boundary sample ``B``;
  partition 1 (the line's last pixel, at distance n) is ``B + n g``, partition 2 (its
  middle pixel) the mean of ``B`` and partition 1, partition 3 the linear interpolation
  between those. In exact arithmetic the three partitions compose into
  ``B + d g`` (``d`` = distance along the line), exact for planes: PDP-H
  ``L[y] + (x+1) gx``, PDP-V ``T[x] + (y+1) gy``, PDP-DDR ``T/L/M`` on the diagonal plus
  ``(min(x, y)+1)(gx+gy)``, PDP-DDL ``T[x+y+1] + (y+1)(gy-gx)``; rounded once at the end.
- PVM (temporal PDP): the previous frame's pixel-varying map ``map = prev - PDP_d(prev_nb)``
  (per pixel, co-located block) is added to ``PDP_d(nb)`` of the current frame.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

SHIFT = 12
HIP4_NAMES = ("V", "H", "DC", "DDL", "DDR", "VR", "HD", "VL", "HU")
HIP16_NAMES = ("V", "H", "DC", "Plane")
PDP_NAMES = ("PDP-H", "PDP-V", "PDP-DDL", "PDP-DDR")


def n_neighbours(n: int) -> int:
    return 3 * n + 1


class _Basis:
    """Neighbour accessors returning basis row vectors (K,) in exact float arithmetic."""

    def __init__(self, n: int):
        self.n, self.k = n, n_neighbours(n)

    def e(self, i: int) -> np.ndarray:
        v = np.zeros(self.k)
        v[i] = 1.0
        return v

    def M(self) -> np.ndarray:
        return self.e(0)

    def T(self, i: int) -> np.ndarray:  # T[-1] is the corner
        return self.M() if i < 0 else self.e(1 + i)

    def L(self, j: int) -> np.ndarray:  # L[-1] is the corner
        return self.M() if j < 0 else self.e(1 + 2 * self.n + j)


class _Transposed:
    """A :class:`_Basis` seen transposed: top and left neighbours swapped."""

    def __init__(self, b: _Basis):
        self.n, self.T, self.L, self.M = b.n, b.L, b.T, b.M


def _hip_pixel(b: _Basis, mode: int, y: int, x: int) -> tuple[np.ndarray, int]:
    """(weights, shift) of one pixel of a nine-mode H.264 predictor (N = 4 or 8)."""
    n, T, L, M = b.n, b.T, b.L, b.M
    if mode == 0:
        return T(x), 0
    if mode == 1:
        return L(y), 0
    if mode == 2:
        return sum(T(i) for i in range(n)) + sum(L(j) for j in range(n)), int(np.log2(2 * n))
    if mode == 3:  # diagonal down-left
        if x == y == n - 1:
            return T(2 * n - 2) + 3 * T(2 * n - 1), 2
        return T(x + y) + 2 * T(x + y + 1) + T(x + y + 2), 2
    if mode == 4:  # diagonal down-right
        if x > y:
            return T(x - y - 2) + 2 * T(x - y - 1) + T(x - y), 2
        if x < y:
            return L(y - x - 2) + 2 * L(y - x - 1) + L(y - x), 2
        return T(0) + 2 * M() + L(0), 2
    if mode == 5:  # vertical-right
        z = 2 * x - y
        if z >= 0 and z % 2 == 0:
            return T(x - (y >> 1) - 1) + T(x - (y >> 1)), 1
        if z >= 0:
            return T(x - (y >> 1) - 2) + 2 * T(x - (y >> 1) - 1) + T(x - (y >> 1)), 2
        if z == -1:
            return L(0) + 2 * M() + T(0), 2
        return L(y - 2 * x - 1) + 2 * L(y - 2 * x - 2) + L(y - 2 * x - 3), 2
    if mode == 6:  # horizontal-down: vertical-right transposed (x <-> y, top <-> left)
        return _hip_pixel(_Transposed(b), 5, x, y)
    if mode == 7:  # vertical-left
        if y % 2 == 0:
            return T(x + (y >> 1)) + T(x + (y >> 1) + 1), 1
        return T(x + (y >> 1)) + 2 * T(x + (y >> 1) + 1) + T(x + (y >> 1) + 2), 2
    if mode == 8:  # horizontal-up
        z = x + 2 * y
        if z < 2 * n - 3 and z % 2 == 0:
            return L(y + (x >> 1)) + L(y + (x >> 1) + 1), 1
        if z < 2 * n - 3:
            return L(y + (x >> 1)) + 2 * L(y + (x >> 1) + 1) + L(y + (x >> 1) + 2), 2
        if z == 2 * n - 3:
            return L(n - 2) + 3 * L(n - 1), 2
        return L(n - 1), 0
    raise ValueError(mode)


def _pdp_pixel(b: _Basis, mode: int, y: int, x: int) -> np.ndarray:
    """Exact (rational) weights of one pixel of a spatial PDP mode (0 H, 1 V, 2 DDL, 3 DDR)."""
    n, T, L, M = b.n, b.T, b.L, b.M
    gx = (T(n - 1) - M()) / n
    gy = (L(n - 1) - M()) / n
    if mode == 0:
        return L(y) + (x + 1) * gx
    if mode == 1:
        return T(x) + (y + 1) * gy
    if mode == 2:
        return T(x + y + 1) + (y + 1) * (gy - gx)
    if mode == 3:
        d = min(x, y) + 1
        base = T(x - y - 1) if x > y else (L(y - x - 1) if x < y else M())
        return base + d * (gx + gy)
    raise ValueError(mode)


@lru_cache(maxsize=None)
def hip_matrices(n: int) -> np.ndarray:
    """Integer HIP matrices (modes, N*N, K) at shift :data:`SHIFT` (Plane excluded for N=16)."""
    b = _Basis(n)
    if n == 16:
        rows = []
        for mode in range(3):
            m = mode if mode < 2 else 2
            rows.append([_hip_pixel(b, m, y, x) for y in range(n) for x in range(n)])
    else:
        rows = [[_hip_pixel(b, m, y, x) for y in range(n) for x in range(n)] for m in range(9)]
    out = np.array([[w * 2.0 ** (SHIFT - s) for w, s in mode] for mode in rows])
    assert np.array_equal(out, np.rint(out))
    return out.astype(np.int64)


@lru_cache(maxsize=None)
def pdp_matrices(n: int) -> np.ndarray:
    """Integer PDP matrices (4, N*N, K) at shift :data:`SHIFT` (exact: weights are dyadic)."""
    b = _Basis(n)
    out = np.array([[_pdp_pixel(b, m, y, x) * 2.0**SHIFT for y in range(n) for x in range(n)]
                    for m in range(4)])
    assert np.array_equal(out, np.rint(out))
    return out.astype(np.int64)


@lru_cache(maxsize=None)
def _float_weights(n: int, which: str) -> np.ndarray:
    """Cached (K, modes * N*N) float64 transposed weights: 'hip', 'pdp' or 'hip+pdp'."""
    parts = {"hip": [hip_matrices(n)], "pdp": [pdp_matrices(n)], "hip+pdp": [hip_matrices(n), pdp_matrices(n)]}
    w = np.concatenate(parts[which], 0)
    return np.ascontiguousarray(w.reshape(-1, n_neighbours(n)).T.astype(np.float64))


def apply_matrices(nb: np.ndarray, w: np.ndarray | str, n: int | None = None) -> np.ndarray:
    """``(W @ nb + 2**(S-1)) >> S`` for neighbour vectors (..., K) -> (..., modes, N*N) int64.

    ``w`` is an integer array (modes, N*N, K) or the name of a cached set (with ``n``).
    Computed as one float64 BLAS product; exact because every partial sum stays below
    2**53 (|nb| < 2**16, |weights| < 2**15, K <= 49).
    """
    k = nb.shape[-1]
    if isinstance(w, str):
        wt = _float_weights(n, w)
    else:
        wt = w.reshape(-1, k).T.astype(np.float64)
    acc = nb.reshape(-1, k).astype(np.float64) @ wt
    acc += 2.0 ** (SHIFT - 1)
    acc *= 2.0**-SHIFT
    np.floor(acc, out=acc)
    nn = (n or int(round(np.sqrt(w.shape[1])))) ** 2
    return acc.astype(np.int64).reshape(*nb.shape[:-1], -1, nn)


def plane16(nb: np.ndarray) -> np.ndarray:
    """H.264 intra 16x16 Plane prediction (sec. 8.3.3.4) for nb (..., 49) -> (..., 256) int64."""
    nb = nb.astype(np.int64)
    t = np.concatenate([nb[..., :1], nb[..., 1:17]], -1)  # T[-1..15]
    lft = np.concatenate([nb[..., :1], nb[..., 33:49]], -1)  # L[-1..15]
    xp = np.arange(8)
    hh = ((xp + 1) * (t[..., 9 + xp] - t[..., 7 - xp])).sum(-1)
    vv = ((xp + 1) * (lft[..., 9 + xp] - lft[..., 7 - xp])).sum(-1)
    a = 16 * (lft[..., 16] + t[..., 16])
    bb = (5 * hh + 32) >> 6
    cc = (5 * vv + 32) >> 6
    yy, xx = np.divmod(np.arange(256), 16)
    return (a[..., None] + bb[..., None] * (xx - 7) + cc[..., None] * (yy - 7) + 16) >> 5


@lru_cache(maxsize=None)
def filter8_matrix() -> np.ndarray:
    """(25, 25) integer taps of the H.264 8x8 reference sample filter (sec. 8.3.2.2.1, all
    samples available): ``nb' = (nb @ F + 2) >> 2``, [1 2 1] along the top row (its last
    sample [1 3]) and the left column (its last sample [1 3]), the corner from its two
    neighbours."""
    f = np.zeros((25, 25), np.int64)
    m, t, lft = 0, (lambda i: 1 + i), (lambda j: 17 + j)

    def put(out, taps):
        for i, w in taps:
            f[i, out] += w

    put(m, [(t(0), 1), (m, 2), (lft(0), 1)])
    put(t(0), [(m, 1), (t(0), 2), (t(1), 1)])
    for x in range(1, 15):
        put(t(x), [(t(x - 1), 1), (t(x), 2), (t(x + 1), 1)])
    put(t(15), [(t(14), 1), (t(15), 3)])
    put(lft(0), [(m, 1), (lft(0), 2), (lft(1), 1)])
    for y in range(1, 7):
        put(lft(y), [(lft(y - 1), 1), (lft(y), 2), (lft(y + 1), 1)])
    put(lft(7), [(lft(6), 1), (lft(7), 3)])
    return f


def filter8(nb: np.ndarray) -> np.ndarray:
    """Filtered 8x8 reference samples (..., 25) int64 (the HIP 8x8 modes predict from these)."""
    return (nb.astype(np.int64) @ filter8_matrix() + 2) >> 2


def spatial_predictions(nb: np.ndarray, n: int, pdp: bool) -> np.ndarray:
    """All spatial predictions (HIP then PDP) for nb (..., K) -> (..., modes, N*N), clipped.
    At 8x8 the HIP modes use the filtered samples (:func:`filter8`), PDP the raw ones."""
    if n == 8:
        parts = [apply_matrices(filter8(nb), "hip", n)] + ([apply_matrices(nb, "pdp", n)] if pdp else [])
        return np.clip(np.concatenate(parts, -2), 0, 65535)
    pred = apply_matrices(nb, "hip+pdp" if pdp else "hip", n)
    if n == 16:
        hip = pred[..., :3, :]
        rest = pred[..., 3:, :]
        pred = np.concatenate([hip, plane16(nb)[..., None, :], rest], -2)
    return np.clip(pred, 0, 65535)


def n_hip_modes(n: int) -> int:
    return 4 if n == 16 else 9


def pvm_maps(prev_blocks: np.ndarray, prev_nb: np.ndarray, n: int) -> np.ndarray:
    """Pixel-varying maps of the previous frame: ``prev - PDP_d(prev_nb)`` -> (..., 4, N*N)."""
    return prev_blocks[..., None, :].astype(np.int64) - apply_matrices(prev_nb, "pdp", n)


def pvm_predictions(nb: np.ndarray, maps: np.ndarray, n: int) -> np.ndarray:
    """Temporal PDP: ``clip(PDP_d(nb) + map_d)`` for nb (..., K), maps (..., 4, N*N)."""
    return np.clip(apply_matrices(nb, "pdp", n) + maps, 0, 65535)
