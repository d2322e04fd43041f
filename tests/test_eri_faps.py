"""MPEG-4 FAPs from 68 landmarks: invariances, zero at neutral, the inverse, FAPUs, signs."""

import numpy as np
import pytest

from facesynth.eri.faps import (
    FAP_NAMES,
    FAP_TABLE,
    FEATURE_POINTS,
    N_FAPS,
    compute_faps,
    face_axes,
    faps_to_landmarks,
    fapu,
)
from facesynth.eri.geometry import extend, forehead_points, mouth_open, open_mouth, select_neutral
from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine
from tests._faces import face_sequence_arrays, face_template, random_similarity


def _frames(n=8, seed=0):
    return face_sequence_arrays(n, seed)[1]


def test_table_is_consistent():
    assert N_FAPS == len(FAP_NAMES) == 36 and len(set(FAP_NAMES)) == N_FAPS
    assert len({r[0] for r in FAP_TABLE}) == N_FAPS  # MPEG-4 numbers unique
    for _, _, fp, direction, unit in FAP_TABLE:
        assert fp in FEATURE_POINTS and direction in ("left", "right", "up", "down")
        assert unit in ("ES", "ENS", "MNS", "MW", "IRISD")
    idx = [i for v in FEATURE_POINTS.values() for i in v]
    assert min(idx) >= 0 and max(idx) < 68


def test_zero_at_neutral_and_invariant_to_similarity(rng):
    lm = _frames()
    neutral = face_template()
    assert np.abs(compute_faps(neutral, neutral)).max() < 1e-3
    ref = compute_faps(lm, neutral)
    assert np.abs(ref).max() > 10  # the frames do carry expressions
    for _ in range(3):  # each frame moved by its own similarity (head motion)
        moved = np.stack([apply_affine(f, random_similarity(rng, angle=0.4, shift=30)) for f in lm])
        np.testing.assert_allclose(compute_faps(moved, neutral), ref, atol=2e-2)
    # the whole recording (neutral included) under one similarity: same FAPs (axes follow the face)
    m = random_similarity(rng, angle=0.5, shift=40)
    np.testing.assert_allclose(compute_faps(apply_affine(lm, m), apply_affine(neutral, m)), ref, atol=2e-2)


def test_fapu_closed_form():
    n = face_template().astype(np.float64)
    units = fapu(n) * 1024
    np.testing.assert_allclose(units[0], np.linalg.norm(n[42:48].mean(0) - n[36:42].mean(0)), rtol=1e-9)
    np.testing.assert_allclose(units[3], np.linalg.norm(n[54] - n[48]), rtol=1e-9)
    upper_l, lower_l = n[[43, 44]].mean(0), n[[46, 47]].mean(0)
    upper_r, lower_r = n[[37, 38]].mean(0), n[[40, 41]].mean(0)
    np.testing.assert_allclose(units[4], 0.5 * (np.linalg.norm(upper_l - lower_l) + np.linalg.norm(upper_r - lower_r)))
    # the template is upright: ENS and MNS are plain y differences
    np.testing.assert_allclose(units[1], n[33, 1] - 0.5 * (n[36:48].mean(0)[1] + n[36:48].mean(0)[1]), rtol=1e-6)
    np.testing.assert_allclose(units[2], n[62, 1] - n[33, 1], rtol=1e-9)


def test_inverse_round_trip_same_person():
    lm, neutral = _frames(10, 3), face_template()
    f = compute_faps(lm, neutral)
    back = faps_to_landmarks(neutral, f)
    np.testing.assert_allclose(compute_faps(back, neutral), f, atol=1e-2)
    # FAP-driven points land where the aligned frames put them along the FAP axes
    i62 = 62
    from facesynth.eri.faps import align_to_neutral

    aligned = align_to_neutral(lm, neutral)
    np.testing.assert_allclose(back[:, i62, 1], aligned[:, i62, 1], atol=1e-3)


def test_inverse_scales_with_the_targets_fapus(rng):
    f = compute_faps(_frames(6, 1), face_template())
    small = face_template()
    big = apply_affine(small, np.array([[2.0, 0, 5], [0, 2.0, -7]]))
    d_small = faps_to_landmarks(small, f) - small
    d_big = faps_to_landmarks(big, f) - big
    np.testing.assert_allclose(d_big, 2 * d_small, atol=1e-3)
    # a rotated target moves along its own axes
    m = random_similarity(rng, scale=(1, 1), angle=0.4, shift=0)
    rot = apply_affine(small, m)
    np.testing.assert_allclose(faps_to_landmarks(rot, f) - rot, d_small @ m[:, :2].T, atol=1e-3)


@pytest.mark.parametrize("name, point, axis, sign", [
    ("open_jaw", 8, 1, 1), ("raise_l_i_eyebrow", 22, 1, -1), ("stretch_l_cornerlip", 64, 0, 1),
    ("stretch_r_cornerlip_o", 48, 0, -1), ("close_t_r_eyelid", 37, 1, 1), ("squeeze_l_eyebrow", 22, 0, -1),
])
def test_sign_conventions(name, point, axis, sign):
    n = face_template()
    f = np.zeros((1, N_FAPS), np.float32)
    f[0, FAP_NAMES.index(name)] = 100.0
    d = faps_to_landmarks(n, f)[0] - n
    assert np.sign(d[point, axis]) == sign and abs(d[point, 1 - axis]) < 1e-4
    assert np.abs(d[[27, 30, 36, 45]]).max() < 1e-5  # anchors stay


def test_errors():
    n = face_template()
    with pytest.raises(FacesynthError, match="68, 2"):
        compute_faps(np.zeros((3, 5, 2)), n)
    with pytest.raises(FacesynthError, match="faps must have shape"):
        faps_to_landmarks(n, np.zeros((2, 7)))
    closed = n.copy()
    closed[[37, 38, 40, 41, 43, 44, 46, 47], 1] = n[36, 1]
    with pytest.raises(FacesynthError, match="IRISD"):
        fapu(closed)
    nan = n.copy()
    nan[3] = np.nan
    with pytest.raises(FacesynthError, match="NaN"):
        compute_faps(nan, n)


def test_geometry_helpers():
    n = face_template()
    lm = _frames(6)
    assert face_axes(n) @ np.array([1.0, 0]) == pytest.approx([1, 0], abs=1e-6)
    fh = forehead_points(n, 0.25)
    assert fh.shape == (10, 2) and (fh[:, 1] < n[17:27, 1]).all()
    ext = extend(lm, n, fh)
    assert ext.shape == (6, 78, 2)
    np.testing.assert_allclose(extend(n, n, fh)[0, 68:], fh, atol=1e-4)
    opened = open_mouth(n, 0.1)
    assert mouth_open(opened[None, :68])[0] > mouth_open(n[None])[0] + 0.05
    idx, info = select_neutral(np.concatenate([lm, opened[None, :68]]), mouth_closed_max=1.0)
    assert idx < len(lm) or info["mouth_open"] <= 1.0


@pytest.mark.shared
def test_real_clip_faps(shared_clip_dir):
    lm = np.load(shared_clip_dir("lp_d6") / "landmarks.npy")[::8]
    i, info = select_neutral(lm)
    assert info["mouth_open"] <= 0.03
    f = compute_faps(lm, lm[i])
    assert np.abs(f[i]).max() < 1e-2
    back = faps_to_landmarks(lm[i], f)
    np.testing.assert_allclose(compute_faps(back, lm[i]), f, atol=0.05)
    jaw = f[:, FAP_NAMES.index("open_jaw")]
    assert jaw.max() > 300  # the clip opens the mouth wide (FAPU MNS ~ 40 px / 1024)


def test_free_points_follow_affine_fields_with_a_closed_mouth(rng):
    """The thin-plate spline reproduces affine displacement fields exactly, also when the
    inner lips of the neutral face coincide (closed mouth, as dlib's integer points give)."""
    from facesynth.eri.faps import _interpolation

    n = face_template().astype(np.float64)
    n[[61, 62, 63]] = n[[67, 66, 65]]
    w, rest, ctrl = _interpolation(n)
    a = np.array([[0.05, -0.02], [0.03, 0.04]])
    field = n @ a.T + [1.5, -2.0]
    np.testing.assert_allclose(w @ field[ctrl], field[rest], atol=1e-3)
    f = np.zeros((1, N_FAPS), np.float32)
    f[0, FAP_NAMES.index("open_jaw")] = 500
    d = faps_to_landmarks(n, f)[0] - n
    assert np.abs(d).max() <= np.abs(d[8]).max() + 1e-6  # nothing overshoots the chin
    assert d[7, 1] > 0 and d[9, 1] > 0  # jaw beside the chin follows it down
