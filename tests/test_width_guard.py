"""model.width_guard (facesynth.runs.width_guard): the widest reference width whose validation PSNR
costs at most the guard against 128 px, its candidates, its frame PSNR against the evaluation's,
the fallback, the recorded choice's round trip and a bad setting."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.eval.frame_level import frame_level, psnr_common
from facesynth.eval.sadm_eval import EvalConfig
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.artifact import load_face_model
from facesynth.model.reference import reference_width
from facesynth.model.restore import slice_stops
from facesynth.runs import width_guard as wg
from facesynth.runs.config import compose_config
from facesynth.runs.training import run_training
from facesynth.sadm.fit import SADMConfig

SMALL = ["regressor=linear", "data.n_frames=48", "data.size=256", "sadm.augment_copies=0", "sadm.region_shrink=false",
         "eval.noise=[0.0]", "eval.frame_level=false", "eval.train_level=false", "eval.talking_head=false", "quiet=true"]


@pytest.mark.parametrize("psnr, guard, want", [
    ([30.0, 29.95, 29.70], 0.10, 176),  # the middle one within the guard, the widest beyond it
    ([30.0, 29.95, 29.70], 0.30, 224),  # both within
    ([30.0, 29.95, 29.70], 0.0, 128),  # no cost allowed: the base
    ([30.0, 29.50, 29.95], 0.10, 224),  # not monotone: the widest within the guard, not the first that fails
    ([30.0, 29.00, 28.00], 0.50, 128),  # every wider one costs more: the base
    ([30.0, 30.20, 30.10], 0.0, 224),  # gains cost nothing
])
def test_choose_width_on_hand_made_curves(psnr, guard, want):
    assert wg.choose_width([128, 176, 224], psnr, guard) == want


def test_choose_width_takes_the_worst_slice():
    psnr = [[30.0, 28.0, 31.0], [29.95, 28.2, 31.5], [30.5, 27.8, 32.0]]  # per width, per slice
    assert wg.choose_width([128, 192, 256], psnr, 0.1) == 192  # 256 gains on two slices, loses 0.2 dB on one
    assert wg.choose_width([128, 192, 256], psnr, 0.2) == 256


def test_slice_stops():
    assert slice_stops(100, 15) == [55, 70, 85, 100]  # the last four blocks of 15 rows
    assert slice_stops(60, 10) == [30, 40, 50, 60]
    assert slice_stops(40, 10) == [30, 40]  # too few rows for a fit before the earlier blocks
    assert slice_stops(25, 10) == [25]  # the filter guard's one slice (and gap)
    assert slice_stops(20, 10) == [20]  # its slice without a gap


def test_candidate_widths():
    assert wg.candidate_widths(256) == [128, 192, 256]
    assert wg.candidate_widths(176) == [128, 160, 176]
    assert wg.candidate_widths(144) == [128, 144]  # no multiple of 16 strictly between
    assert wg.candidate_widths(128) == [128] and wg.candidate_widths(96) == [96]


@pytest.mark.parametrize("bad", [-0.1, "abc", float("nan"), float("inf"), True, [0.1]])
def test_a_bad_guard_is_one_line_naming_the_field(bad):
    with pytest.raises(FacesynthError, match=r"^model\.width_guard must be") as err:
        wg.check_width_guard(bad)
    assert "\n" not in str(err.value)
    assert wg.check_width_guard(None) is None and wg.check_width_guard(0) == 0.0 and wg.check_width_guard("0.2") == 0.2


def test_training_refuses_a_bad_guard_before_writing(tmp_path):
    with pytest.raises(FacesynthError, match=r"model\.width_guard must be"):
        run_training(compose_config(SMALL + ["model.width_guard=-0.5"]), tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def synthetic():
    seq = make_synthetic_sequence(40, 256, seed=3)
    rows = np.arange(30)
    return seq, rows


def test_psnr_common_is_the_evaluations_common_region_figure(synthetic):
    """psnr_common against frame_level's pooled ``common.whole`` at sigma 0 for the same textures."""
    seq, rows = synthetic
    model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(reference_width=96), rows=rows, progress=False)
    test = np.arange(32, 40)
    pred = np.clip(model.sample_textures(seq, test, progress=False) + 0.03, 0, 1).astype(np.float32)  # not the frame itself
    cfg = EvalConfig(noise=[0.0], max_test_frames=None)
    pooled, _, _ = frame_level(model, lambda lm: pred, seq, test, pred, pred, cfg, 0, ["0"], lambda lm, s, seed: lm,
                               common=seq.landmarks[test])
    got = psnr_common(model, pred, seq, test, seq.landmarks[test], cfg.feather)
    assert got == pytest.approx(pooled["common"]["whole"]["sadm"]["0"], abs=1e-6)
    assert got < 60  # a real error, not a perfect match


def test_the_guard_falls_back_to_128_when_the_wider_width_costs_more(synthetic, monkeypatch):
    seq, rows = synthetic
    want = reference_width("auto", seq.landmarks[rows])
    assert want > 128  # the synthetic faces are wider than the base: two candidates at least
    seen = []

    def fake(model, pred, seq_, val, common, feather):  # the base 30 dB, every wider width `lose` dB lower
        seen.append((model.config.reference_width, model.meta["train_frames"], tuple(val)))
        return 30.0 - (lose if model.config.reference_width > 128 else 0.0)

    monkeypatch.setattr(wg, "psnr_common", fake)
    cfg = FaceModelConfig(reference_width="auto", width_guard=0.2)
    sadm_cfg = SADMConfig(augment_sigma=0.0, region_shrink=False)
    lose = 1.0
    model, tex, report = wg.guard_width(seq, seq, rows, cfg, "linear", {}, sadm_cfg, seq.landmarks, 2.0)
    assert report["chosen"] == 128 and model.config.reference_width == 128
    assert tex.shape == (len(rows), model.n_channels * model.n_pixels) and model.meta["train_frames"] == len(rows)
    widths = wg.candidate_widths(want)
    assert [c["width"] for c in report["candidates"]] == widths
    assert [c["cost_db"] for c in report["candidates"]] == [0.0] + [1.0] * (len(widths) - 1)
    n_val = round(len(rows) * 0.15)
    stops = slice_stops(len(rows), n_val)
    assert report["slices"] == [{"val_rows": [s - n_val, s], "fit_frames": s - 2 * n_val} for s in stops]
    # every slice scored by a model fitted on the rows before it and its gap, never on the slice
    assert seen == [(w, s - 2 * n_val, tuple(rows[s - n_val : s])) for w in widths for s in stops]
    assert model.meta["width_guard"] == report
    lose = 0.1  # within the guard: the widest
    model, _, report = wg.guard_width(seq, seq, rows, cfg, "linear", {}, sadm_cfg, seq.landmarks, 2.0)
    assert report["chosen"] == want and model.config.reference_width == want


def test_the_recorded_choice_round_trips(tmp_path):
    """A training run with the guard: metrics.json, the face model's meta and config.yaml agree, and
    the choice is the chooser's on the recorded figures."""
    metrics = run_training(compose_config(SMALL + ["model.reference_width=auto", "model.width_guard=0.1"]), tmp_path)
    report = metrics["width_guard"]
    assert json.loads((tmp_path / "metrics.json").read_text())["width_guard"] == report
    model = load_face_model(tmp_path / "face_model")
    assert model.meta["width_guard"] == report and model.config.reference_width == report["chosen"]
    assert model.config.width_guard == 0.1 and yaml.safe_load((tmp_path / "config.yaml").read_text())["model"]["width_guard"] == 0.1
    widths = [c["width"] for c in report["candidates"]]
    psnr = np.array([c["psnr_db"] for c in report["candidates"]])
    assert len(widths) >= 2 and psnr.shape == (len(widths), len(report["slices"])) and np.isfinite(psnr).all()
    assert report["chosen"] == wg.choose_width(widths, psnr, 0.1)
    assert [c["cost_db"] for c in report["candidates"]] == pytest.approx((psnr[0] - psnr).max(1))
