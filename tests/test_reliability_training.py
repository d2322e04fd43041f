"""Issue 15, training (rows 4, 7, 13, 14): landmarks outside the frames are refused on
loading, a plain-colour video is refused before any artifact is written, a tiny training
set is warned about, Hydra config errors exit 2 and list only the regressor options."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from facesynth.data import load_sequence
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.runs.config import CONF_DIR, register_configs
from facesynth.runs.training import run_training

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clip():
    seq = make_synthetic_sequence(n_frames=12, size=128, seed=4)
    return seq.load_frames(), seq.landmarks


def _npz(path: Path, frames, lm) -> Path:
    np.savez(path, frames=frames, landmarks=lm)
    return path


def _cfg(path: Path, *overrides: str):
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["regressor=linear", "data=video", f"data.path={path}",
                                                         "eval.noise=[0.0]", "eval.train_level=false", *overrides])


@pytest.mark.parametrize("how", ["x10", "plus5000", "offset"])
def test_row4_landmarks_outside_the_frame_are_refused_on_loading(clip, tmp_path, how):
    frames, lm = clip
    bad = {"x10": lm * 10, "plus5000": lm + 5000, "offset": lm - 200}[how]
    path = _npz(tmp_path / "c.npz", frames, bad)
    with pytest.raises(FacesynthError, match=r"c\.npz: landmarks of 12 of 12 rows .* outside the 128x128 frame"):
        load_sequence(path)
    out = tmp_path / "run"
    with pytest.raises(FacesynthError, match="outside"):
        run_training(_cfg(path), out)
    assert not out.exists() or sorted(p.name for p in out.iterdir()) == []


def test_row7_plain_colour_video_is_refused_before_any_artifact(clip, tmp_path):
    frames, lm = clip
    path = _npz(tmp_path / "plain.npz", np.full_like(frames, 90), lm)
    out = tmp_path / "run"
    with pytest.raises(FacesynthError, match="same colour"):
        run_training(_cfg(path), out)
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml"]  # no face_model/, sadm/ or metrics.json


def test_row13_small_training_set_is_warned_about(clip, tmp_path, caplog):
    frames, lm = clip
    path = _npz(tmp_path / "small.npz", frames[:8], lm[:8])
    with caplog.at_level("WARNING"):
        run_training(_cfg(path), tmp_path / "run")
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("training and" in w and "mean little" in w for w in warnings), warnings
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_row13_more_landmark_rows_than_frames_are_refused(clip, tmp_path):
    frames, lm = clip
    with pytest.raises(FacesynthError, match="12 landmark frames but only 6 image frames"):
        load_sequence(_npz(tmp_path / "c.npz", frames[:6], lm))


@pytest.mark.parametrize("override, needle", [("regressor=svrr", "Available options in 'regressor'"),
                                              ("seed=abc", "seed"), ("data.nope=1", "nope")])
def test_row14_hydra_config_errors_exit_2(tmp_path, override, needle):
    r = subprocess.run([sys.executable, str(ROOT / "train.py"), override, f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 2, r.stderr[-1000:]
    assert needle in r.stderr and "Traceback" not in r.stderr
    if override == "regressor=svrr":
        assert "_schema" not in r.stderr
        assert {"krr", "linear", "mlp", "poly2", "svr"} <= {line.strip() for line in r.stderr.splitlines()}
    assert not (tmp_path / "run").exists()


def test_row7_non_finite_metrics_leave_no_artifacts(clip, tmp_path, monkeypatch):
    """The second line of defence: metrics are serialised (strict JSON) before face_model/
    and sadm/ are written, so a non-finite figure leaves no half run."""
    from facesynth.runs import training

    real = training.evaluate_sadm

    def inf_psnr(*a, **k):
        metrics, extras = real(*a, **k)
        metrics["psnr_ref"] = {"sadm": {"0": float("inf")}}
        return metrics, extras

    monkeypatch.setattr(training, "evaluate_sadm", inf_psnr)
    frames, lm = clip
    out = tmp_path / "run"
    with pytest.raises(FacesynthError, match=r"metrics\.json: .*psnr_ref\.sadm\.0"):
        run_training(_cfg(_npz(tmp_path / "c.npz", frames, lm)), out)
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml"]
