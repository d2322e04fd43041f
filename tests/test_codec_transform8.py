"""The 8x8 integer transform against the standard's equations and its closed form."""

import numpy as np
import pytest

from facesynth.codec import transform8 as t8
from facesynth.codec.bitstream import decode_video, encode_video
from facesynth.codec.frame import CodecConfig, read_frame
from facesynth.codec.geometry import build_layout, geometry_video
from facesynth.codec.sources import height_field_mesh
from facesynth.codec.transform import qstep


def _spec_1d(d):
    """ITU-T H.264 sec. 8.5.13.2, one row, in Python integers (>> is a floor shift)."""
    e0, e2 = d[0] + d[4], d[0] - d[4]
    e1 = -d[3] + d[5] - d[7] - (d[7] >> 1)
    e3 = d[1] + d[7] - d[3] - (d[3] >> 1)
    e4 = (d[2] >> 1) - d[6]
    e5 = -d[1] + d[7] + d[5] + (d[5] >> 1)
    e6 = d[2] + (d[6] >> 1)
    e7 = d[3] + d[5] + d[1] + (d[1] >> 1)
    f0, f1, f2, f3 = e0 + e6, e1 + (e7 >> 2), e2 + e4, e3 + (e5 >> 2)
    f4, f5, f6, f7 = e2 - e4, (e3 >> 2) - e5, e0 - e6, e7 - (e1 >> 2)
    return [f0 + f7, f2 + f5, f4 + f3, f6 + f1, f6 - f1, f4 - f3, f2 - f5, f0 - f7]


def _spec_inverse(d):
    rows = [_spec_1d([int(v) for v in r]) for r in d]
    cols = [_spec_1d([rows[i][j] for i in range(8)]) for j in range(8)]
    return np.array([[(cols[j][i] + 128) >> 8 for j in range(8)] for i in range(8)])


def test_basis_is_orthogonal_and_zigzag_is_a_permutation():
    g = t8.T8 @ t8.T8.T
    np.testing.assert_array_equal(g, np.diag([512, 578, 320, 578, 512, 578, 320, 578]))
    assert sorted(t8.ZIGZAG8.tolist()) == list(range(64))
    assert t8.ZIGZAG8[:10].tolist() == [0, 1, 8, 16, 9, 2, 3, 10, 17, 24]


def test_inverse_matches_the_standard_and_its_closed_form(rng):
    d = rng.integers(-(1 << 20), 1 << 20, (30, 8, 8))
    d[:5, 3:] = 0
    got = t8.inverse8(d)
    for k in range(len(d)):
        np.testing.assert_array_equal(got[k], _spec_inverse(d[k]))
    closed = np.einsum("uy,nuv,vx->nyx", t8.T8, d, t8.T8) / 2.0**14  # T^T D T / 64 / 256
    assert np.abs(got - closed).max() <= 1.0


@pytest.mark.parametrize("qp", [0, 7, 30, 54, 87])
def test_float_inverse_is_exact_and_forward_is_t_x_tt(qp, rng):
    z = rng.integers(-4000, 4000, (200, 64))
    z[:40] = 0
    np.testing.assert_array_equal(t8.inverse_slots_float(z.astype(float), qp), t8.inverse_slots(z, qp))
    x = rng.integers(-65535, 65536, (20, 8, 8))
    w = np.einsum("uy,nyx,vx->nuv", t8.T8, x, t8.T8).reshape(20, 64)
    samples = x.reshape(20, 64)[:, t8.SAMPLE_YX[:, 0] * 8 + t8.SAMPLE_YX[:, 1]]
    np.testing.assert_array_equal(samples.astype(float) @ t8.FWD64, w[:, t8.SLOT_UV[:, 0] * 8 + t8.SLOT_UV[:, 1]])
    # steps follow the 4x4 path's Qstep within 3 %
    assert np.abs(t8.step(qp) / qstep(qp) - 1).max() < 0.03


def test_quantised_round_trip_error_is_within_a_step(rng):
    x = rng.integers(-30000, 30000, (100, 64))
    for qp in (0, 24, 48):
        w = x.astype(float) @ t8.FWD64
        z = np.sign(w) * np.floor(np.abs(w) * t8.PF64 / t8.step(qp) + 0.5)
        rec = t8.inverse_slots(z, qp)
        rms = np.sqrt(((rec - x) ** 2).mean())
        assert rms <= 0.5 * qstep(qp) + 1


def test_streams_with_and_without_the_8x8_transform(rng):
    m = height_field_mesh(33, n_frames=3)
    lay = build_layout(m["faces"], m["uv"], (32, 48))
    vid, _ = geometry_video(lay, m["frames"])
    sizes = {}
    for t8_on in (True, False):
        for gop in (1, 3):
            cfg = CodecConfig(qp=36, gop=gop, block_sizes=(8, 16), transform8=t8_on)
            data, rec, _ = encode_video(vid, cfg, lay.mask)
            np.testing.assert_array_equal(decode_video(data)[0], rec)
            sizes[t8_on, gop] = len(data)
            hdr = 4 + 68 + 8  # stream header + CRC, first chunk header
            assert bool(data[hdr + 1] & 128) == t8_on  # the frame header's transform flag
    # a 4x4 frame claiming the 8x8 transform is malformed
    with pytest.raises(ValueError, match="8x8 transform"):
        read_frame(bytes([0, 4 | 128, 2]) + b"\0" * 4, (True, False, False), (3, 32, 48))
