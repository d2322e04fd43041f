"""Core transform, quantisation and entropy-coding round trips."""

import numpy as np
import pytest

from facesynth.codec import entropy
from facesynth.codec.transform import (
    CF,
    code_residual,
    decode_residual,
    dequantise,
    forward4,
    from_sub4,
    inverse4,
    qstep,
    quantise,
    to_sub4,
)

# H.264 post-scaling factors: a^2, ab/2, b^2/4 with a = 1/2, b = sqrt(2/5); the standard's
# integer multipliers approximate PF / Qstep within 3 % (8066 vs 8290 at ab/2 positions)
_PF = np.array([[0.25, np.sqrt(0.1) / 2, 0.25, np.sqrt(0.1) / 2],
                [np.sqrt(0.1) / 2, 0.1, np.sqrt(0.1) / 2, 0.1]] * 2)


def test_forward_is_cf_x_cft_and_inverse_undoes_it(rng):
    x = rng.integers(-65535, 65536, (50, 4, 4))
    w = forward4(x)
    np.testing.assert_array_equal(w[0], CF @ x[0] @ CF.T)
    # the integer inverse equals the float one, Ci^T W Ci / 64, up to rounding
    ci = np.array([[1, 1, 1, 1], [1, 0.5, -0.5, -1], [1, -1, -1, 1], [0.5, -1, 1, -0.5]])
    z = rng.integers(-3000, 3000, (50, 4, 4))
    ref = np.einsum("ji,njk,kl->nil", ci, z.astype(float), ci) / 64
    assert np.abs(inverse4(z) - ref).max() <= 1.0
    # QP 4 (step 1): quantise -> rescale -> inverse recovers x within a few units of 65535
    rec = inverse4(dequantise(quantise(w, 4), 4))
    assert np.abs(rec - x).max() <= 8


@pytest.mark.parametrize("qp", [0, 12, 30, 51, 70, 87])
def test_quantisation_matches_float_closed_form(qp, rng):
    x = rng.integers(-65535, 65536, (200, 4, 4))
    w = forward4(x)
    z = quantise(w, qp)
    ideal = w * _PF / qstep(qp)  # float H.264 quantiser, before the dead-zone rounding
    assert np.all(np.abs(z - ideal) < 1.0 + 0.03 * np.abs(ideal))
    rec = inverse4(dequantise(z, qp))
    # float reconstruction from the same levels: Cf^-1 (Z Qstep / PF) Cf^-T
    ci = np.linalg.inv(CF.astype(float))
    ref = np.einsum("ij,njk,lk->nil", ci, z * qstep(qp) / _PF, ci)
    assert np.abs(rec - ref).max() <= 2.0 + 0.03 * np.abs(ref).max()
    assert np.sqrt(((rec - x) ** 2).mean()) < 0.6 * qstep(qp) + 2


def test_residual_round_trips_and_lossless_bypass(rng):
    for n in (4, 8, 16):
        res = rng.integers(-65535, 65536, (3, 5, n * n))
        np.testing.assert_array_equal(from_sub4(to_sub4(res, n), n), res)
        lev, rec = code_residual(res, n, None)
        np.testing.assert_array_equal(rec, res)
        np.testing.assert_array_equal(decode_residual(lev, n, None), res)
        for qp in (0, 24, 48):
            lev, rec = code_residual(res, n, qp)
            np.testing.assert_array_equal(decode_residual(lev, n, qp), rec)
            assert np.sqrt(((rec - res) ** 2).mean()) < 0.6 * qstep(qp) + 1


def test_error_grows_with_qp(rng):
    yy, xx = np.mgrid[0:16, 0:16]
    res = (3000 * np.sin(xx / 3.0) * np.cos(yy / 5.0)).astype(np.int64).reshape(1, 256)
    errs = [np.abs(code_residual(res, 16, qp)[1] - res).mean() for qp in (0, 18, 36, 54)]
    assert errs == sorted(errs) and errs[0] < 1


def test_entropy_round_trip_with_escapes_and_modes(rng):
    lv = np.round(rng.laplace(size=(3000, 16)) * np.linspace(4, 0.1, 16)).astype(np.int64)
    lv[::2] = 0
    lv[5, 3], lv[7, 0], lv[9, 15] = 70000, -(1 << 30), 15
    modes = rng.integers(0, 13, (3, 6, 7))
    mvs = rng.integers(-4, 5, (20, 2))
    enc = entropy.RangeEncoder()
    entropy.encode_levels(enc, lv)
    entropy.encode_modes(enc, modes, 13)
    entropy.encode_mvs(enc, mvs, 4)
    dec = entropy.RangeDecoder(enc.get_compressed())
    np.testing.assert_array_equal(entropy.decode_levels(dec, len(lv)), lv)
    np.testing.assert_array_equal(entropy.decode_modes(dec, modes.shape, 13), modes)
    np.testing.assert_array_equal(entropy.decode_mvs(dec, 20, 4), mvs)


def test_adaptive_contexts_beat_the_static_bound(rng):
    # all-zero blocks cost almost nothing once the model has adapted
    lv = np.zeros((20000, 16), np.int64)
    lv[rng.integers(0, 20000, 200), 0] = 1
    enc = entropy.RangeEncoder()
    entropy.encode_levels(enc, lv)
    bits = 32 * enc.get_compressed().size
    assert bits < 0.15 * len(lv)


@pytest.mark.parametrize("qp", [24, 48, 72])
def test_transform_domain_distortion_matches_pixel_ssd(qp, rng):
    from facesynth.codec.transform import analyse_residual

    res = rng.integers(-5000, 5000, (300, 64))
    lev, rec = code_residual(res, 8, qp)
    lev2, dist = analyse_residual(res, 8, qp)
    np.testing.assert_array_equal(lev2, lev)
    ssd = ((res - rec) ** 2).sum(-1)
    # Parseval on the (scaled-orthogonal) core transform; the integer inverse adds rounding
    np.testing.assert_allclose(dist, ssd, rtol=0.05, atol=64 * 6)
