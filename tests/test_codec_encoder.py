"""The encoder's fast paths against the decoder's reference arithmetic."""

import numpy as np
import pytest

from facesynth.codec import intra
from facesynth.codec.bitstream import decode_video, encode_video
from facesynth.codec.blocks import sub_order, sub_perm
from facesynth.codec.encoder import encoder_weights
from facesynth.codec.frame import CodecConfig
from facesynth.codec.geometry import build_layout, geometry_video
from facesynth.codec.sources import height_field_mesh
from facesynth.codec.transform import FWD16, ZIGZAG, dequantise, forward4, inverse4, inverse_sub, to_sub4


@pytest.mark.parametrize("n", [4, 8, 16])
def test_sub_block_major_order_is_to_sub4(n):
    x = np.arange(n * n)
    np.testing.assert_array_equal(x[sub_perm(n)].reshape(-1, 4, 4), to_sub4(x, n)[sub_order(n)])


def test_matrix_transforms_equal_the_integer_butterflies(rng):
    x = rng.integers(-65535, 65536, (200, 4, 4))
    zz = forward4(x).reshape(-1, 16)[:, ZIGZAG]
    np.testing.assert_array_equal(x.reshape(-1, 16).astype(float) @ FWD16, zz)  # zigzag output
    for qp in (0, 7, 30, 54, 87):
        z = rng.integers(-3000, 3000, (300, 4, 4))
        z[:50] = 0
        ref = inverse4(dequantise(z, qp))
        got = inverse_sub(z.reshape(-1, 16)[:, ZIGZAG].astype(float), qp)  # zigzag in, raster out
        np.testing.assert_array_equal(got.reshape(-1, 4, 4), ref)


@pytest.mark.parametrize("n", [4, 8, 16])
def test_scaled_float_weights_round_like_the_integer_shift(n, rng):
    nb = rng.integers(0, 65536, (64, intra.n_neighbours(n)))
    nb[:8] = 65535  # extremes
    nb[8:16] = 0
    pred = np.floor(nb.astype(float) @ encoder_weights(n, True, False) + 0.5).reshape(64, -1, n * n)
    if n == 8:  # the encoder feeds the HIP 8x8 columns with the filtered samples
        nbf = np.floor(nb.astype(float) @ (intra.filter8_matrix() * 0.25) + 0.5)
        pred[:, :9] = np.floor(nbf @ encoder_weights(n, True, False)[:, :9 * 64] + 0.5).reshape(64, 9, 64)
    ref = intra.spatial_predictions(nb, n, pdp=True)  # HIP (Plane at slot 3 for 16) then PDP, clipped
    inv = np.argsort(sub_perm(n))
    got = np.clip(pred[..., inv], 0, 65535)
    if n == 16:  # the encoder fills Plane separately
        got[:, 3] = ref[:, 3]
    np.testing.assert_array_equal(got, ref)


def test_batched_all_intra_gives_the_sequential_bitstream():
    m = height_field_mesh(33, n_frames=6)
    lay = build_layout(m["faces"], m["uv"], (32, 48))
    vid, _ = geometry_video(lay, m["frames"])
    one = encode_video(vid, CodecConfig(qp=30, gop=1, batch_frames=1, size_refresh=2), lay.mask)
    many = encode_video(vid, CodecConfig(qp=30, gop=1, batch_frames=4, size_refresh=2), lay.mask)
    assert one[0] == many[0]
    np.testing.assert_array_equal(one[1], many[1])
    np.testing.assert_array_equal(decode_video(many[0])[0], many[1])


def test_grid_groups_put_every_context_neighbour_in_an_earlier_group():
    from facesynth.codec.entropy import grid_groups

    shape = (3, 5, 7)
    group = np.empty(int(np.prod(shape)), int)
    for k, g in enumerate(grid_groups(shape)):
        group[g] = k
    group = group.reshape(shape)
    assert sorted(np.concatenate(grid_groups(shape)).tolist()) == list(range(group.size))
    assert (group[:, 1:, :] > group[:, :-1, :]).all()  # above
    assert (group[:, :, 1:] > group[:, :, :-1]).all()  # left
    assert (group[1:] > group[:-1]).all()  # previous channel


def test_levels_with_neighbour_contexts_round_trip_and_pay_off(rng):
    from facesynth.codec import entropy

    shape = (3, 24, 32)
    active = np.zeros(shape, bool)
    active[:, 4:12, 6:20] = True  # clustered non-zero sub-blocks, as around a face's features
    lv = np.round(rng.laplace(size=(*shape, 16)) * np.linspace(3, 0.1, 16)).astype(np.int64)
    lv[~active] = 0
    lv[0, 5, 7, 2] = 70000  # an escape
    lv = lv.reshape(-1, 16)
    sizes = {}
    for key, shp in (("grid", shape), ("flat", None)):
        enc = entropy.RangeEncoder()
        entropy.encode_levels(enc, lv, shp)
        words = enc.get_compressed()
        sizes[key] = words.size
        np.testing.assert_array_equal(entropy.decode_levels(entropy.RangeDecoder(words), len(lv), shp), lv)
    assert sizes["grid"] < sizes["flat"]


def test_adaptive_model_ages_counts_identically_on_both_sides(rng):
    from facesynth.codec import entropy

    n = 60000  # one context gets far more than LIMIT / 4 symbols: its counts are halved repeatedly
    ctx = (rng.random(n) < 0.02).astype(np.int64)
    sym = np.where(ctx == 0, (rng.random(n) < 0.1).astype(np.int64), rng.integers(0, 5, n))
    m_enc, m_dec = entropy.AdaptiveModel(2, 5), entropy.AdaptiveModel(2, 5)
    enc = entropy.RangeEncoder()
    for s, e in entropy._chunks(n):
        enc.encode(sym[s:e].astype(np.int32), entropy._CAT, m_enc.probs(ctx[s:e]))
        m_enc.update(ctx[s:e], sym[s:e])
    dec = entropy.RangeDecoder(enc.get_compressed())
    out = np.concatenate([m_dec.update(ctx[s:e], v) or v for s, e in entropy._chunks(n)
                          for v in [np.asarray(dec.decode(entropy._CAT, m_dec.probs(ctx[s:e])), np.int64)]])
    np.testing.assert_array_equal(out, sym)
    np.testing.assert_array_equal(m_enc.counts, m_dec.counts)
    assert m_enc.counts[0].sum() <= entropy.LIMIT and m_enc.counts[0].sum() > entropy.LIMIT / 4  # aged, not reset


@pytest.mark.parametrize("kw", [
    dict(qp=0, gop=3, pdp=False, pvm=True, inter=True),
    dict(qp=87, gop=2, rd_candidates=0),
    dict(qp=None, gop=3, block_sizes=(8, 16)),
    dict(qp=45, gop=3, block_sizes=(4, 8, 16), transform8=False, mv_range=1),
    dict(qp=33, gop=1, block_sizes=(16,), pdp=False, batch_frames=2, size_refresh=1),
    dict(qp=51, gop=4, inter=False, block_sizes=(4, 16)),
], ids=["qp0-pvm-no-pdp", "qp87-all-candidates", "lossless-8-16", "4x4-transform", "hip-16-batched", "pvm-no-inter"])
def test_unusual_settings_stay_bit_exact(kw):
    m = height_field_mesh(33, n_frames=4)
    lay = build_layout(m["faces"], m["uv"], (32, 48))
    vid, _ = geometry_video(lay, m["frames"])
    data, rec, _ = encode_video(vid, CodecConfig(**kw), lay.mask)
    np.testing.assert_array_equal(decode_video(data)[0], rec)
    if kw["qp"] is None:
        np.testing.assert_array_equal(rec, vid)
