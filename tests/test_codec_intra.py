"""Each intra mode against a direct per-pixel implementation of its formula."""

from fractions import Fraction

import numpy as np
import pytest

from facesynth.codec import intra


def _nb(rng, n, lo=0, hi=65536):
    return rng.integers(lo, hi, intra.n_neighbours(n)).astype(np.int64)


def _split(nb, n):
    m = int(nb[0])
    t = [int(v) for v in nb[1:2 * n + 1]]
    lft = [int(v) for v in nb[2 * n + 1:]]
    T = lambda i: m if i == -1 else t[i]  # noqa: E731
    L = lambda j: m if j == -1 else lft[j]  # noqa: E731
    return m, T, L


def _ref_hip(nb, n, mode):
    """H.264 sec. 8.3.1.2 / 8.3.2.2 (8x8 spelling, no reference filtering), pixel by pixel."""
    m, T, L = _split(nb, n)
    out = np.zeros((n, n), np.int64)
    for y in range(n):
        for x in range(n):
            if mode == 0:
                v = T(x)
            elif mode == 1:
                v = L(y)
            elif mode == 2:
                v = (sum(T(i) for i in range(n)) + sum(L(j) for j in range(n)) + n) // (2 * n)
            elif mode == 3:
                v = ((T(2 * n - 2) + 3 * T(2 * n - 1) + 2) >> 2 if x == y == n - 1
                     else (T(x + y) + 2 * T(x + y + 1) + T(x + y + 2) + 2) >> 2)
            elif mode == 4:
                if x > y:
                    v = (T(x - y - 2) + 2 * T(x - y - 1) + T(x - y) + 2) >> 2
                elif x < y:
                    v = (L(y - x - 2) + 2 * L(y - x - 1) + L(y - x) + 2) >> 2
                else:
                    v = (T(0) + 2 * m + L(0) + 2) >> 2
            elif mode == 5:
                z = 2 * x - y
                if z >= 0 and z % 2 == 0:
                    v = (T(x - (y >> 1) - 1) + T(x - (y >> 1)) + 1) >> 1
                elif z >= 0:
                    v = (T(x - (y >> 1) - 2) + 2 * T(x - (y >> 1) - 1) + T(x - (y >> 1)) + 2) >> 2
                elif z == -1:
                    v = (L(0) + 2 * m + T(0) + 2) >> 2
                else:
                    v = (L(y - 2 * x - 1) + 2 * L(y - 2 * x - 2) + L(y - 2 * x - 3) + 2) >> 2
            elif mode == 6:
                z = 2 * y - x
                if z >= 0 and z % 2 == 0:
                    v = (L(y - (x >> 1) - 1) + L(y - (x >> 1)) + 1) >> 1
                elif z >= 0:
                    v = (L(y - (x >> 1) - 2) + 2 * L(y - (x >> 1) - 1) + L(y - (x >> 1)) + 2) >> 2
                elif z == -1:
                    v = (L(0) + 2 * m + T(0) + 2) >> 2
                else:
                    v = (T(x - 2 * y - 1) + 2 * T(x - 2 * y - 2) + T(x - 2 * y - 3) + 2) >> 2
            elif mode == 7:
                i = x + (y >> 1)
                v = (T(i) + T(i + 1) + 1) >> 1 if y % 2 == 0 else (T(i) + 2 * T(i + 1) + T(i + 2) + 2) >> 2
            else:
                z = x + 2 * y
                j = y + (x >> 1)
                if z > 2 * n - 3:
                    v = L(n - 1)
                elif z == 2 * n - 3:
                    v = (L(n - 2) + 3 * L(n - 1) + 2) >> 2
                elif z % 2 == 0:
                    v = (L(j) + L(j + 1) + 1) >> 1
                else:
                    v = (L(j) + 2 * L(j + 1) + L(j + 2) + 2) >> 2
            out[y, x] = v
    return out.ravel()


def _ref_plane16(nb):
    m, T, L = _split(nb, 16)
    hh = sum((x + 1) * (T(8 + x) - T(6 - x)) for x in range(8))
    vv = sum((y + 1) * (L(8 + y) - L(6 - y)) for y in range(8))
    a, b, c = 16 * (L(15) + T(15)), (5 * hh + 32) >> 6, (5 * vv + 32) >> 6
    return np.array([min(max((a + b * (x - 7) + c * (y - 7) + 16) >> 5, 0), 65535)
                     for y in range(16) for x in range(16)])


def _ref_pdp(nb, n, mode):
    """Three-partition progressive prediction along each directional line, in exact
    rational arithmetic: partition 1 = the line's far pixel (B + len*g), partition 2 =
    its middle pixel (mean of B and partition 1), partition 3 = linear interpolation."""
    m, T, L = _split(nb, n)
    gx, gy = Fraction(T(n - 1) - m, n), Fraction(L(n - 1) - m, n)
    step = {0: (0, 1), 1: (1, 0), 2: (1, -1), 3: (1, 1)}[mode]  # (dy, dx) per step
    g = {0: gx, 1: gy, 2: gy - gx, 3: gx + gy}[mode]
    out = {}
    for y in range(n):
        for x in range(n):
            # walk back to the boundary to find the line's start
            d, yy, xx = 0, y, x
            while yy >= 0 and xx >= 0:
                yy, xx, d = yy - step[0], xx - step[1], d + 1
            base = T(xx) if yy == -1 else L(yy)
            # walk forward to the line's last pixel inside the block
            length, yy, xx = d, y, x
            while 0 <= yy + step[0] < n and 0 <= xx + step[1] < n:
                yy, xx, length = yy + step[0], xx + step[1], length + 1
            p1 = base + length * g  # partition 1
            mid = Fraction(length, 2)
            p2 = (base + p1) / 2  # partition 2 (at distance length / 2)
            if d == length:
                v = p1
            elif d <= mid:  # partition 3: interpolate on the known points
                v = base + (p2 - base) * d / mid
            else:
                v = p2 + (p1 - p2) * (d - mid) / (length - mid)
            out[y, x] = int(min(max(np.floor(v + Fraction(1, 2)), 0), 65535))
    return np.array([out[y, x] for y in range(n) for x in range(n)])


def _ref_filter8(nb):
    """H.264 sec. 8.3.2.2.1 reference sample filtering, sample by sample (all available)."""
    m, T, L = _split(nb, 8)
    t = [T(i) for i in range(16)]
    lft = [L(j) for j in range(8)]
    tf = [(m + 2 * t[0] + t[1] + 2) >> 2] + [(t[x - 1] + 2 * t[x] + t[x + 1] + 2) >> 2 for x in range(1, 15)]
    tf.append((t[14] + 3 * t[15] + 2) >> 2)
    lf = [(m + 2 * lft[0] + lft[1] + 2) >> 2] + [(lft[y - 1] + 2 * lft[y] + lft[y + 1] + 2) >> 2 for y in range(1, 7)]
    lf.append((lft[6] + 3 * lft[7] + 2) >> 2)
    mf = (t[0] + 2 * m + lft[0] + 2) >> 2
    return np.array([mf] + tf + lf, np.int64)


@pytest.mark.parametrize("n", [4, 8])
def test_nine_hip_modes_match_per_pixel_formulas(n, rng):
    for _ in range(3):
        nb = _nb(rng, n)
        pred = intra.spatial_predictions(nb[None], n, pdp=False)[0]
        ref_nb = _ref_filter8(nb) if n == 8 else nb  # 8x8 modes predict from filtered samples
        np.testing.assert_array_equal(intra.filter8(nb[None])[0] if n == 8 else nb, ref_nb)
        for mode in range(9):
            np.testing.assert_array_equal(pred[mode], _ref_hip(ref_nb, n, mode), err_msg=f"mode {mode}")


def test_h264_4x4_textbook_values():
    # M=10, A..H = 20..90 step 10 (T), I..L = 1..4 (left)
    nb = np.array([10, 20, 30, 40, 50, 60, 70, 80, 90, 1, 2, 3, 4])
    p = intra.spatial_predictions(nb[None], 4, pdp=False)[0].reshape(9, 4, 4)
    assert p[2, 0, 0] == (20 + 30 + 40 + 50 + 1 + 2 + 3 + 4 + 4) >> 3
    assert p[4, 0, 0] == (20 + 2 * 10 + 1 + 2) >> 2  # DDR a = (A + 2M + I + 2) >> 2
    assert p[3, 3, 3] == (80 + 3 * 90 + 2) >> 2  # DDL p = (G + 3H + 2) >> 2
    assert p[8, 3, 3] == 4  # HU bottom-right = L


def test_sixteen_modes_and_plane(rng):
    for _ in range(3):
        nb = _nb(rng, 16)
        pred = intra.spatial_predictions(nb[None], 16, pdp=False)[0]
        assert pred.shape == (4, 256)
        for mode in range(3):
            np.testing.assert_array_equal(pred[mode], _ref_hip(nb, 16, mode))
        np.testing.assert_array_equal(pred[3], _ref_plane16(nb))


@pytest.mark.parametrize("n", [4, 8, 16])
def test_pdp_modes_match_progressive_reference(n, rng):
    for _ in range(2):
        nb = _nb(rng, n, 20000, 40000)
        pred = intra.spatial_predictions(nb[None], n, pdp=True)[0][intra.n_hip_modes(n):]
        for mode in range(4):
            np.testing.assert_array_equal(pred[mode], _ref_pdp(nb, n, mode), err_msg=f"PDP {mode}")


@pytest.mark.parametrize("n", [4, 8, 16])
def test_pdp_is_exact_on_planes(n):
    a, b, c = 30000, 37, -21
    T = [a + b * i - c for i in range(2 * n)]
    L = [a - b + c * j for j in range(n)]
    nb = np.array([a - b - c] + T + L)
    pred = intra.spatial_predictions(nb[None], n, pdp=True)[0][intra.n_hip_modes(n):]
    yy, xx = np.divmod(np.arange(n * n), n)
    for mode in range(4):
        np.testing.assert_array_equal(pred[mode], a + b * xx + c * yy)


def test_pvm_adds_previous_pixel_varying_map(rng):
    n = 4
    prev_nb, cur_nb = _nb(rng, n), _nb(rng, n)
    prev_blk = rng.integers(0, 65536, n * n)
    maps = intra.pvm_maps(prev_blk[None], prev_nb[None], n)[0]
    pred = intra.pvm_predictions(cur_nb[None], maps[None], n)[0]
    for mode in range(4):
        ref_map = prev_blk - _ref_pdp(prev_nb, n, mode)
        # _ref_pdp clips; the map uses the unclipped PDP, equal when nothing clips
        unclipped = np.clip(_ref_pdp(cur_nb, n, mode) + ref_map, 0, 65535)
        ok = (_ref_pdp(prev_nb, n, mode) > 0) & (_ref_pdp(prev_nb, n, mode) < 65535)
        ok &= (_ref_pdp(cur_nb, n, mode) > 0) & (_ref_pdp(cur_nb, n, mode) < 65535)
        np.testing.assert_array_equal(pred[mode][ok], unclipped[ok])
