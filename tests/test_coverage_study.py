"""The coverage meter's study (bench/studies/coverage_heldout.py) and the meter's distance
(facesynth.coverage.distance), against independent references: scikit-learn's
neighbours, scipy's Spearman correlation and sign test, the textbook partial correlation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest, spearmanr
from sklearn.neighbors import NearestNeighbors

from bench.studies.coverage_heldout import partial_spearman, per_frame_study, shape_distance, within_clips
from facesynth import coverage
from facesynth.geometry import apply_affine, generalised_procrustes, similarity_fit


def test_distance_is_the_mean_over_the_nearest_frames_and_reach_its_clipped_complement():
    rng = np.random.default_rng(0)
    frames, shapes = rng.normal(0, 1, (50, 8)), rng.normal(0, 1, (20, 8))
    dist, _ = NearestNeighbors(n_neighbors=coverage.NEAREST).fit(frames).kneighbors(shapes)
    np.testing.assert_allclose(coverage.distance(frames, shapes), dist.mean(1), atol=1e-12)
    np.testing.assert_allclose(coverage.reach(frames, shapes), np.clip(1 - dist.mean(1) / coverage.REACH, 0, 1), atol=1e-12)


def test_partial_spearman_is_the_textbook_partial_correlation_of_ranks():
    rng = np.random.default_rng(1)
    t = rng.normal(0, 1, 80)
    x, y = t + rng.normal(0, 1, 80), t + 0.5 * rng.normal(0, 1, 80)
    r = lambda a, b: spearmanr(a, b)[0]  # noqa: E731
    want = (r(x, y) - r(x, t) * r(y, t)) / np.sqrt((1 - r(x, t) ** 2) * (1 - r(y, t) ** 2))
    assert partial_spearman(x, y, t) == pytest.approx(want, abs=1e-12)
    assert abs(partial_spearman(t + 0.01 * rng.normal(0, 1, 80), rng.normal(0, 1, 80), t)) < 0.3


def test_the_per_frame_study_correlates_within_each_clip():
    """Per clip Spearman of minus the reading with the target (scipy), NaN targets left out;
    the median, positives and the sign test (scipy) over the clips."""
    rng = np.random.default_rng(2)
    data, want = {}, {}
    for k in range(7):
        n = 20 + 3 * k
        near = rng.uniform(0, 2, n)
        psnr = 30 - (1 if k < 5 else -1) * near + rng.normal(0, 0.5, n) + 5 * k  # two clips the wrong way
        lp = rng.uniform(0, 1, n)
        lp[0] = np.nan
        time = np.arange(n) / 15.0
        rd = {"meter": near, "time": time}
        data[f"c{k}"] = (rd, {"psnr": psnr, "lpips": -lp})
        want[f"c{k}"] = (spearmanr(-near, psnr)[0], spearmanr(-near[1:], -lp[1:])[0], partial_spearman(-near, psnr, time))
    out = per_frame_study(data, np.random.default_rng(0))
    assert set(out) == {"meter", "time", "meter_time_fixed"}
    got = out["meter"]["psnr"]
    assert got["per_clip"] == {c: round(w[0], 3) for c, w in want.items()}
    assert out["meter"]["lpips"]["per_clip"] == {c: round(w[1], 3) for c, w in want.items()}
    assert out["meter_time_fixed"]["psnr"]["per_clip"] == {c: round(w[2], 3) for c, w in want.items()}
    v = np.array([w[0] for w in want.values()])
    assert got["median"] == round(float(np.median(v)), 3) and got["positive"] == int((v > 0).sum()) == 5 and got["clips"] == 7
    assert got["sign_p"] == round(binomtest(5, 7).pvalue, 4)
    assert got["median_95"][0] <= got["median"] <= got["median_95"][1]


def test_within_clips_leaves_out_clips_without_a_correlation():
    s = within_clips({"a": 0.5, "b": float("nan"), "c": -0.1, "d": 0.3}, np.random.default_rng(0), n_boot=200)
    assert s["clips"] == 3 and s["positive"] == 2 and s["median"] == 0.3


def test_shape_distance_aligns_to_the_recording_and_counts_the_nearest_shapes():
    """A recorded shape moved, scaled and turned is at distance 0 of its own; other shapes'
    distances are scikit-learn's neighbours among the Procrustes-aligned recording."""
    rng = np.random.default_rng(3)
    base = rng.normal(0, 1, (68, 2))
    rec = base + rng.normal(0, 0.05, (30, 68, 2))
    a = 1.7 * np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
    moved = rec[5] @ a.T + np.array([40.0, -7.0])
    assert shape_distance(rec, moved[None], 1)[0] == pytest.approx(0, abs=1e-9)
    others = base + rng.normal(0, 0.1, (6, 68, 2))
    aligned, mean = generalised_procrustes(rec)
    q = apply_affine(others, similarity_fit(others, mean[None]))
    dist, _ = NearestNeighbors(n_neighbors=3).fit(aligned.reshape(30, -1)).kneighbors(q.reshape(6, -1))
    np.testing.assert_allclose(shape_distance(rec, others, 3), dist.mean(1), atol=1e-12)
