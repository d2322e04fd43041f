"""Block grids, wavefront schedules and the prediction/reconstruction steps shared by the
encoder and the decoder (so that both run the very same integer arithmetic).

A frame of C channels, H x W (multiples of 16), is cut into N x N blocks. Reconstructed
samples live in a padded buffer (C, H+1, W+1) whose first row and column hold the
constant ``2**15`` (unavailable neighbours). Block (by, bx) needs its left, top-left,
top and top-right neighbours, so all blocks with the same ``bx + 2 by`` (a wavefront)
are independent and are predicted together, batched over the channels too.
Above-right samples beyond the right edge repeat ``T[N-1]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from facesynth.codec import intra

MID = 1 << 15


@dataclass(frozen=True)
class Grid:
    n: int
    height: int
    width: int
    nb_idx: np.ndarray  # (nblk, K) flat indices into the padded buffer
    pix_idx: np.ndarray  # (nblk, N*N) flat indices of each block's samples
    waves: tuple  # tuple of (b,) int arrays of block ids
    order: np.ndarray  # (nblk,) block ids in wavefront order (waves concatenated)
    bounds: tuple  # (start, end) of each wave in ``order``

    @property
    def shape(self) -> tuple[int, int]:
        return self.height // self.n, self.width // self.n

    @property
    def n_blocks(self) -> int:
        return self.nb_idx.shape[0]


@lru_cache(maxsize=16)
def grid(n: int, height: int, width: int) -> Grid:
    """Block grid of size ``n`` over an ``height x width`` frame (multiples of 16)."""
    nby, nbx = height // n, width // n
    wp = width + 1
    by, bx = np.divmod(np.arange(nby * nbx), nbx)
    y0, x0 = by * n + 1, bx * n + 1  # block origin in the padded buffer
    i = np.arange(2 * n)
    tcol = x0[:, None] + i[None, :]
    tcol = np.where(tcol > width, x0[:, None] + n - 1, tcol)  # repeat T[N-1] past the edge
    t_idx = (y0 - 1)[:, None] * wp + tcol
    l_idx = (y0[:, None] + np.arange(n)[None, :]) * wp + (x0 - 1)[:, None]
    m_idx = ((y0 - 1) * wp + x0 - 1)[:, None]
    nb_idx = np.concatenate([m_idx, t_idx, l_idx], 1)
    yy, xx = np.divmod(np.arange(n * n), n)
    pix_idx = (y0[:, None] + yy[None, :]) * wp + x0[:, None] + xx[None, :]
    t = bx + 2 * by
    waves = tuple(np.nonzero(t == k)[0] for k in range(int(t.max()) + 1))
    order = np.concatenate(waves)
    ends = np.cumsum([len(wv) for wv in waves])
    bounds = tuple(zip((ends - np.array([len(wv) for wv in waves])).tolist(), ends.tolist(), strict=True))
    return Grid(n, height, width, nb_idx, pix_idx, waves, order, bounds)


@lru_cache(maxsize=None)
def sub_order(n: int) -> np.ndarray:
    """(S,) raster index of each 4x4 sub-block of an N x N block in the encoder's order:
    8x8 quadrants in raster order, the four sub-blocks of each in raster order (the
    identity for N <= 8), so that every 8x8 block is a contiguous run of samples."""
    s = n // 4
    if s <= 2:
        return np.arange(s * s)
    qy, qx, ay, ax = np.meshgrid(np.arange(s // 2), np.arange(s // 2), np.arange(2), np.arange(2), indexing="ij")
    return ((2 * qy + ay) * s + 2 * qx + ax).ravel()


@lru_cache(maxsize=None)
def sub_perm(n: int) -> np.ndarray:
    """(N*N,) raster positions of a block's samples in sub-block-major order: the 4x4
    sub-blocks in :func:`sub_order`, each in raster order (so (..., N*N) reshapes to
    (..., (N/4)^2, 16), and to (..., (N/8)^2, 64) 8x8 blocks, without a copy)."""
    s = n // 4
    sb = sub_order(n)
    sy, sx = np.divmod(sb, s)
    py, px = np.divmod(np.arange(16), 4)
    return ((sy[:, None] * 4 + py[None, :]) * n + sx[:, None] * 4 + px[None, :]).ravel()


def padded(frame: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (C, (H+1)*(W+1)) int64 with the constant border."""
    c, h, w = frame.shape
    out = np.full((c, h + 1, w + 1), MID, np.int64)
    out[:, 1:, 1:] = frame
    return out.reshape(c, -1)


def unpadded(buf: np.ndarray, height: int, width: int) -> np.ndarray:
    return buf.reshape(-1, height + 1, width + 1)[:, 1:, 1:]


@dataclass(frozen=True)
class ModeSet:
    """Which candidate predictors a frame offers, in index order:
    HIP (9 or 4), PDP spatial (4), PVM temporal (4), inter (1)."""

    n: int
    pdp: bool
    pvm: bool
    inter: bool

    @property
    def n_hip(self) -> int:
        return intra.n_hip_modes(self.n)

    @property
    def n_spatial(self) -> int:
        return self.n_hip + (4 if self.pdp else 0)

    @property
    def n_predictive(self) -> int:  # modes whose prediction depends on the current frame
        return self.n_spatial + (4 if self.pvm else 0)

    @property
    def n_modes(self) -> int:
        return self.n_predictive + (1 if self.inter else 0)

    @property
    def inter_mode(self) -> int:
        return self.n_predictive if self.inter else -1

    def names(self) -> list[str]:
        hip = intra.HIP16_NAMES if self.n == 16 else intra.HIP4_NAMES
        out = [f"HIP-{m}" for m in hip]
        out += list(intra.PDP_NAMES) if self.pdp else []
        out += [f"PVM-{m[4:]}" for m in intra.PDP_NAMES] if self.pvm else []
        return out + (["INTER"] if self.inter else [])


def sad_maps(cur: np.ndarray, prev: np.ndarray, rng: int) -> tuple[np.ndarray, np.ndarray]:
    """SAD of every 4x4 block for every integer displacement in [-rng, rng]^2.

    cur, prev : (C, H, W). Returns (displacements (D, 2) sorted by |dy|+|dx|,
    SADs (D, C, H/4, W/4)); block sums are two matrix products per displacement.
    """
    c, h, w = cur.shape
    pp = np.pad(prev.astype(np.float32), ((0, 0), (rng, rng), (rng, rng)), mode="edge")
    cands = sorted(((dy, dx) for dy in range(-rng, rng + 1) for dx in range(-rng, rng + 1)),
                   key=lambda d: (abs(d[0]) + abs(d[1]), d))
    rows = (np.arange(h)[None, :] // 4 == np.arange(h // 4)[:, None]).astype(np.float32)  # (H/4, H)
    cols = (np.arange(w)[:, None] // 4 == np.arange(w // 4)[None, :]).astype(np.float32)  # (W, W/4)
    cur = cur.astype(np.float32)
    sads = np.empty((len(cands), c, h // 4, w // 4), np.float64)
    for i, (dy, dx) in enumerate(cands):
        sads[i] = rows @ np.abs(cur - pp[:, rng + dy:rng + dy + h, rng + dx:rng + dx + w]) @ cols
    return np.asarray(cands, np.int64), sads


def motion_search(cur: np.ndarray, prev: np.ndarray, n: int, rng: int,
                  sads: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Full-search block motion estimation (integer pel, SAD; ties -> smaller |mv|).

    cur, prev : (C, H, W); ``sads``: :func:`sad_maps` output, reused across block sizes.
    Returns (C, nblk, 2) int64 displacements (dy, dx) in [-rng, rng].
    """
    cands, s4 = sads if sads is not None else sad_maps(cur, prev, rng)
    d, c, h4, w4 = s4.shape
    k = n // 4
    s = s4.reshape(d, c, h4 // k, k, w4 // k, k).sum((3, 5)).reshape(d, c, -1)
    return cands[np.argmin(s, 0)]


def motion_compensate(prev: np.ndarray, mvs: np.ndarray, n: int, rng: int) -> np.ndarray:
    """Blocks of ``prev`` (C, H, W) displaced by ``mvs`` (C, nblk, 2) -> (C, nblk, N*N)."""
    c, h, w = prev.shape
    pp = np.pad(prev.astype(np.int64), ((0, 0), (rng, rng), (rng, rng)), mode="edge")
    nbx = w // n
    by, bx = np.divmod(np.arange((h // n) * nbx), nbx)
    yy, xx = np.divmod(np.arange(n * n), n)
    rows = rng + by[None, :, None] * n + mvs[..., 0:1] + yy
    cols = rng + bx[None, :, None] * n + mvs[..., 1:2] + xx
    return pp[np.arange(c)[:, None, None], rows, cols]
