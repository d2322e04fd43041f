"""Zero-phase smoothing of tracked landmarks (facesynth.data.smoothing, data.smooth_landmarks)."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter, savgol_filter

from facesynth.data import FaceSequence
from facesynth.data.config import DataConf
from facesynth.data.smoothing import (
    FAST_RADII_S,
    LIGHT_SHIFT_PX,
    SIGMA_MOVING_S,
    SIGMA_STILL_S,
    segments,
    smooth_sequence,
    smooth_track,
    split_bounds,
)
from facesynth.errors import FacesynthError
from facesynth.eval.common_region import common_landmarks
from facesynth.rundir import load_data, read_config

RATE = 30.0


def face(n: int, seed: int = 0) -> np.ndarray:
    """(n, 68, 2) a still face: 68 points on a ring of radius 60 px around (240, 240)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, 68, endpoint=False)
    pts = np.stack([240 + 60 * np.cos(ang), 240 + 60 * np.sin(ang)], -1) + rng.normal(0, 3, (68, 2))
    return np.repeat(pts[None], n, 0)


def jitter(lm: np.ndarray, seed: int = 1) -> np.ndarray:
    """A tracker's whole pixels: the true points moved by 0.4 px noise, then rounded."""
    return np.round(lm + np.random.default_rng(seed).normal(0, 0.4, lm.shape))


def motion(x: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(np.diff(x, axis=0), axis=-1)))


def test_a_ramp_passes_without_lag_as_savitzky_golay_keeps_it():
    t = np.arange(90, dtype=np.float64)
    lm = face(90) + t[:, None, None] * np.array([1.5, -0.7])  # the whole face drifts at constant speed
    out = smooth_track(lm, RATE)
    ref = savgol_filter(lm, 15, 2, axis=0)  # polynomial smoothing reproduces a ramp exactly, ends included
    np.testing.assert_allclose(ref, lm, atol=1e-9)
    np.testing.assert_allclose(out, ref, atol=2e-4)  # float32 output: no lag, at the ends too


def test_zero_phase_on_a_sine_where_a_causal_filter_lags():
    t = np.arange(300, dtype=np.float64)
    x = 5 * np.sin(2 * np.pi * t / 60)  # 0.5 Hz at 30 frames/s
    lm = face(300) + x[:, None, None]
    out = smooth_track(lm, RATE, fast_radii_s=1e9)[:, 0, 0] - lm[0, 0, 0]  # the strong filter alone
    causal = lfilter([0.2], [1, -0.8], x)  # a one-pole smoother: lags

    def lag(y):  # the shift (frames) of y against x, from the cross-correlation's peak in the interior
        c = [np.dot(x[50:250], y[50 + k:250 + k]) for k in range(-10, 11)]
        return int(np.argmax(c)) - 10

    assert lag(out) == 0
    assert lag(causal) >= 2
    assert np.abs(out - x)[30:-30].max() < 0.05 * 5  # the amplitude of a slow move is kept


def test_a_still_face_loses_its_jitter():
    true = face(120)
    tracked = jitter(true)
    out = smooth_track(tracked, RATE)
    assert motion(tracked) >= 0.5
    assert motion(out) < 0.3 * motion(tracked)
    assert np.abs(out - true).mean() < 0.6 * np.abs(tracked - true).mean()  # closer to the truth, not only calmer


def test_a_fast_mouth_move_is_kept_where_a_fixed_filter_flattens_it():
    n = 90
    true = face(n)
    k = np.arange(n)
    pulse = 20 * np.where(np.abs(k - 45) < 5, 0.5 + 0.5 * np.cos(np.pi * (k - 45) / 5), 0.0)  # 9 frames, 20 px
    lips = np.arange(48, 68)
    true[:, lips, 1] += pulse[:, None]
    tracked = jitter(true)
    adaptive = smooth_track(tracked, RATE)
    fixed = smooth_track(tracked, RATE, fast_radii_s=1e9)

    def peak(y):
        return float((y[:, lips, 1] - true[0, lips, 1]).mean(1).max())

    assert peak(fixed) < 0.8 * 20
    assert peak(adaptive) > 0.9 * 20
    assert np.argmax((adaptive[:, lips, 1]).mean(1)) == 45  # no lag at the peak
    still = np.setdiff1d(np.arange(68), lips)
    assert motion(adaptive[:, still]) < 0.3 * motion(tracked[:, still])  # the rest of the face is still smoothed


def test_a_head_moving_in_steps_keeps_its_steps_within_the_centroid_limit():
    """A video with repeated frames (every 6th held, as vrt_face4's): the head moves in steps of
    up to 11 px. The light Gaussian alone (scipy's gaussian_filter1d, the reference) rounds a
    step off by more than a pixel; with the limit, the centroid is the tracked one moved by at
    most LIGHT_SHIFT_PX, and the face's shape is what the filter makes of it without the limit."""
    n = 120
    k = np.arange(n)
    held = np.maximum.accumulate(np.where(k % 6 == 5, k - 1, k))  # frame k shows frame k - 1 every 6th frame
    y = 11 * np.sin(2 * np.pi * held / 24) + 2.0 * held  # a fast nod and drift, every point alike
    tracked = np.round(face(n) + np.stack([np.zeros(n), y], -1)[:, None])  # whole pixels, a rigid face
    c = tracked.mean(1)
    light = gaussian_filter1d(c, SIGMA_MOVING_S * RATE, axis=0, mode="nearest", truncate=4.0)
    inner = slice(10, -10)  # away from the ends' padding
    assert np.abs(light - c)[inner].max() > 1.0  # what the light filter alone does to the steps
    out = smooth_track(tracked, RATE).astype(np.float64)
    free = smooth_track(tracked, RATE, light_shift_px=None).astype(np.float64)
    ref = c + np.clip(light - c, -LIGHT_SHIFT_PX, LIGHT_SHIFT_PX)  # every point moves fast: the light filter alone
    np.testing.assert_allclose(out.mean(1)[inner], ref[inner], atol=2e-4)
    np.testing.assert_allclose(np.abs(free.mean(1) - light)[inner], 0, atol=2e-4)  # without the limit: the light track
    np.testing.assert_allclose((out - out.mean(1, keepdims=True)), free - free.mean(1, keepdims=True), atol=2e-4)


def test_the_centroid_limit_leaves_a_still_face_and_a_talking_mouth_as_they_were():
    still = jitter(face(120))  # the strong filter alone: the light track's limit does not reach it
    np.testing.assert_array_equal(smooth_track(still, RATE), smooth_track(still, RATE, light_shift_px=None))
    n = 90
    true = face(n)
    k = np.arange(n)
    true[:, 48:68, 1] += 20 * np.where(np.abs(k - 45) < 5, 0.5 + 0.5 * np.cos(np.pi * (k - 45) / 5), 0.0)[:, None]
    tracked = jitter(true)
    out, free = smooth_track(tracked, RATE), smooth_track(tracked, RATE, light_shift_px=None)
    np.testing.assert_allclose(out, free, atol=1e-4)  # the opening moves the light track's centroid by < LIGHT_SHIFT_PX
    assert (out[:, 48:68, 1] - true[0, 48:68, 1]).mean(1).max() > 0.9 * 20  # its peak kept
    assert motion(out[:, :48]) < 0.3 * motion(tracked[:, :48])  # still smoothed
    with pytest.raises(FacesynthError, match="light_shift_px"):
        smooth_track(tracked, RATE, light_shift_px=0.0)


def test_segments_cut_at_split_and_breaks():
    fi = np.array([0, 1, 2, 3, 4, 5, 6, 20, 21, 22])
    assert [s.tolist() for s in segments(fi, [3])] == [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9]]
    assert [s.tolist() for s in segments(np.arange(0, 20, 2), [])] == [list(range(10))]  # every 2nd frame: no break
    assert split_bounds(100, 0.75, 4) == [75, 79]


def test_training_and_test_parts_never_see_each_other():
    n = 100
    tracked = jitter(face(n))
    seq = FaceSequence.from_arrays(tracked.astype(np.float32), fps=RATE, name="s")
    bounds = split_bounds(n, 0.75, 0)
    out = smooth_sequence(seq, bounds)
    changed = tracked.copy()
    changed[75:] += 7.0  # another test part
    out2 = smooth_sequence(FaceSequence.from_arrays(changed.astype(np.float32), fps=RATE, name="s"), bounds)
    np.testing.assert_array_equal(out.landmarks[:75], out2.landmarks[:75])
    np.testing.assert_array_equal(out.landmarks[:75], smooth_track(tracked[:75], RATE))
    np.testing.assert_array_equal(out.landmarks[75:], smooth_track(tracked[75:], RATE))
    np.testing.assert_array_equal(out.tracked, seq.landmarks)
    assert out.meta["landmark_smoothing"]["sigma_still_s"] == SIGMA_STILL_S
    np.testing.assert_array_equal(out.subset([3, 80]).tracked, seq.landmarks[[3, 80]])


def test_load_data_smooths_a_video_and_the_judged_region_stays_on_tracked_points(tmp_path):
    n = 40
    np.save(tmp_path / "landmarks.npy", jitter(face(n)).astype(np.float32))
    (tmp_path / "meta.json").write_text('{"video": {"fps": 25.0}}')
    cfg = OmegaConf.structured(DataConf(kind="video", path=str(tmp_path), smooth_landmarks=False))
    plain = load_data(cfg, 0)
    assert plain.tracked is None
    cfg.smooth_landmarks = True
    smoothed = load_data(cfg, 0)
    np.testing.assert_array_equal(smoothed.tracked, plain.landmarks)
    np.testing.assert_array_equal(smoothed.landmarks[:30], smooth_track(plain.landmarks[:30], 25.0))
    np.testing.assert_array_equal(smoothed.landmarks[30:], smooth_track(plain.landmarks[30:], 25.0))
    np.testing.assert_array_equal(common_landmarks(smoothed), plain.landmarks)
    assert smoothed.fingerprint == plain.fingerprint  # the data; the run's config records the smoothing
    assert DataConf().smooth_landmarks  # the default


def test_the_synthetic_subject_is_never_smoothed():
    cfg = OmegaConf.structured(DataConf(kind="synthetic", n_frames=40, size=128, smooth_landmarks=True))
    seq = load_data(cfg, 0)
    assert seq.tracked is None and "landmark_smoothing" not in seq.meta


def test_a_run_from_before_the_setting_reads_as_unsmoothed(tmp_path):
    cfg = OmegaConf.to_container(OmegaConf.structured(DataConf()))
    del cfg["smooth_landmarks"]
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml({"seed": 0, "data": cfg}))
    assert read_config(tmp_path).data.smooth_landmarks is False


def test_the_threshold_is_a_data_setting_and_a_smoothed_run_without_it_reads_as_0_35(tmp_path):
    n = 40
    np.save(tmp_path / "landmarks.npy", jitter(face(n)).astype(np.float32))
    (tmp_path / "meta.json").write_text('{"video": {"fps": 25.0}}')
    cfg = OmegaConf.structured(DataConf(kind="video", path=str(tmp_path), smooth_fast_radii_s=0.5))
    seq = load_data(cfg, 0)
    np.testing.assert_array_equal(seq.landmarks[:30], smooth_track(seq.tracked[:30], 25.0, fast_radii_s=0.5))
    assert seq.meta["landmark_smoothing"]["fast_radii_s"] == 0.5
    assert DataConf().smooth_fast_radii_s == FAST_RADII_S
    run = OmegaConf.to_container(OmegaConf.structured(DataConf(kind="video", path=str(tmp_path))))
    del run["smooth_fast_radii_s"]
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml({"seed": 0, "data": run}))
    assert read_config(tmp_path).data.smooth_fast_radii_s == 0.35
    cfg.smooth_fast_radii_s = 0.0
    with pytest.raises(FacesynthError, match=r"^data.smooth_fast_radii_s must be > 0"):
        load_data(cfg, 0)


def test_the_centroid_limit_is_a_data_setting_and_a_run_without_it_reads_as_no_limit(tmp_path):
    n = 40
    np.save(tmp_path / "landmarks.npy", jitter(face(n)).astype(np.float32))
    (tmp_path / "meta.json").write_text('{"video": {"fps": 25.0}}')
    assert DataConf().smooth_light_shift_px == LIGHT_SHIFT_PX
    for limit in (0.1, None):
        cfg = OmegaConf.structured(DataConf(kind="video", path=str(tmp_path), smooth_light_shift_px=limit))
        seq = load_data(cfg, 0)
        np.testing.assert_array_equal(seq.landmarks[:30], smooth_track(seq.tracked[:30], 25.0, light_shift_px=limit))
        assert seq.meta["landmark_smoothing"]["light_shift_px"] == limit
    run = OmegaConf.to_container(OmegaConf.structured(DataConf(kind="video", path=str(tmp_path))))
    del run["smooth_light_shift_px"]
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml({"seed": 0, "data": run}))
    assert read_config(tmp_path).data.smooth_light_shift_px is None  # trained before the limit: re-evaluated as trained
    cfg.smooth_light_shift_px = -1.0
    with pytest.raises(FacesynthError, match=r"^data.smooth_light_shift_px must be > 0"):
        load_data(cfg, 0)


def test_bad_tracks_are_refused():
    with pytest.raises(FacesynthError, match="NaN"):
        smooth_track(np.full((5, 68, 2), np.nan), RATE)
    with pytest.raises(FacesynthError, match=r"\(T, P, 2\)"):
        smooth_track(np.zeros((5, 68)), RATE)
    with pytest.raises(FacesynthError, match="rate"):
        smooth_track(face(5), 0.0)


def test_the_segment_ends_are_smoothed_too():
    true = face(60)
    tracked = jitter(true, seed=4)
    out = smooth_track(tracked, RATE)
    for end in (0, -1):
        assert np.abs(out[end] - true[end]).mean() < 0.8 * np.abs(tracked[end] - true[end]).mean()


def test_the_benches_smooth_a_tracked_run_as_the_default_trains(tmp_path):
    """bench.studies.landmark_smoothing.run_sequence (also bench.studies.detail --smoothed):
    a run trained on tracked landmarks, from before the centroid's limit, is re-read tracked
    as it was, or smoothed as a run with today's data settings would be (load_data, limit
    0.3 px), on the same split."""
    from bench.studies.landmark_smoothing import run_sequence
    from facesynth.data.splits import temporal_split

    n = 40
    raw = jitter(face(n)).astype(np.float32)
    raw[25:] += np.arange(15, dtype=np.float32)[:, None, None] * np.float32(3.0)  # the head moves: the limit acts
    np.save(tmp_path / "landmarks.npy", raw)
    (tmp_path / "meta.json").write_text('{"video": {"fps": 25.0}}')
    run = OmegaConf.to_container(OmegaConf.structured(DataConf(kind="video", path=str(tmp_path), smooth_landmarks=False)))
    del run["smooth_light_shift_px"]
    (tmp_path / "config.yaml").write_text(OmegaConf.to_yaml({"seed": 0, "data": run}))
    want_tr, want_te = temporal_split(n, DataConf().train_fraction, DataConf().gap)
    default = load_data(OmegaConf.structured(DataConf(kind="video", path=str(tmp_path))), 0)
    unlimited = load_data(OmegaConf.structured(DataConf(kind="video", path=str(tmp_path), smooth_light_shift_px=None)), 0)
    assert not np.array_equal(default.landmarks, unlimited.landmarks)
    for smoothed, want in ((False, raw), (True, default.landmarks)):
        cfg, seq, tr, te, trained_smoothed = run_sequence(tmp_path, smoothed)
        np.testing.assert_array_equal(seq.landmarks, want)
        np.testing.assert_array_equal(tr, want_tr)
        np.testing.assert_array_equal(te, want_te)
        assert trained_smoothed is False and cfg.seed == 0


def test_the_acceptance_against_figures_given_per_clip():
    """bench.studies.perceptual.against_today with today's figures as a mapping (as
    bench.studies.detail --today-json reads them): the issue's points, by hand."""
    from bench.studies.perceptual import against_today

    keys = ("lpips_face", "lpips_mouth", "psnr_frame_common", "sharpness", "flicker_ratio")
    today = {"a": dict(zip(keys, (0.10, 0.20, 30.0, 0.4, 0.8), strict=True)),
             "b": dict(zip(keys, (0.05, 0.10, 25.0, 0.5, 0.9), strict=True)),
             "c": dict(zip(keys, (0.08, 0.30, 28.0, 0.6, 0.7), strict=True))}
    new = {"a__x": {"v": dict(zip(keys, (0.05, 0.16, 29.7, 0.8, 1.1), strict=True))},
           "b__x": {"v": dict(zip(keys, (0.06, 0.05, 25.5, 0.7, 1.0), strict=True))},
           "c__x": {"v": dict(zip(keys, (0.04, 0.21, 28.1, 0.9, 0.9), strict=True))},
           "d__x": {"v": dict(zip(keys, (0.01, 0.01, 40.0, 2.0, 9.0), strict=True))}}  # no figures today: left out
    got = against_today(today, new)["v"]
    assert got["clips"] == 3 and got["lpips_face_not_lower"] == 1
    assert got["lpips_face_change_median"] == pytest.approx(-0.5)
    assert got["lpips_mouth_change_median"] == pytest.approx(-0.3)
    assert got["psnr_change_min_db"] == pytest.approx(-0.3)
    assert (got["sharpness_median"], got["sharpness_max"], got["flicker_ratio_max"]) == (0.8, 0.9, 1.1)
    assert got["ceiling_change_median"]["mouth"] == {"oracle": None, "rewarp": None}  # figures without ceilings
    ceil = {"a": 0.10, "b": 0.07, "c": 0.15}  # the variant's mouth oracle: -50 %, -30 %, -50 % of today's prediction
    for clip, v in ceil.items():
        new[f"{clip}__x"]["v"]["lpips_ceiling"] = {"mouth": {"oracle": v, "rewarp": v / 2}}
    got = against_today(today, new)["v"]["ceiling_change_median"]
    assert got["mouth"]["oracle"] == pytest.approx(-0.5) and got["mouth"]["rewarp"] == pytest.approx(-0.75)
    assert got["face"] == {"oracle": None, "rewarp": None}
