"""SADM: the synthetic subject's known dependence is recovered; run directories, metrics
keys, re-evaluation and the sweep table."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from facesynth.data import temporal_split
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.landmarks import FACE_REGIONS
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.regressors import REGISTRY
from facesynth.runs.config import CONF_DIR, register_configs
from facesynth.sadm.fit import SADMConfig, fit_sadm, load_sadm, save_sadm
from facesynth.sadm.regions import fit_region_shrink, fit_weights, frame_regions, reference_regions

ROOT = Path(__file__).resolve().parents[1]
TINY = ["data.n_frames=64", "data.size=192", "eval.noise=[0,2]", "eval.max_test_frames=3"]


@pytest.fixture(scope="module")
def synthetic():
    seq = make_synthetic_sequence(240, 256, seed=0)
    tr, te = temporal_split(len(seq), 0.75)
    model, tex_tr = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    return seq, tr, te, model, tex_tr


def test_synthetic_dependence_is_recovered(synthetic):
    """Held-out frames: the linear SADM beats the mean texture by a wide margin."""
    seq, tr, te, model, tex_tr = synthetic
    sadm = fit_sadm(model, seq, tr, tex_tr, "linear", {"ridge": 0.0}, SADMConfig(features="bs"))
    m, _ = evaluate_sadm(sadm, seq, tr, te, EvalConfig(noise=[0, 2], frame_level=False, train_level=False))
    ref = m["psnr_ref"]
    assert ref["sadm"]["0"] > ref["mean_texture"]["0"] + 2.0
    assert ref["sadm"]["0"] < ref["oracle"]["0"]
    assert ref["sadm"]["2"] > ref["mean_texture"]["2"]
    assert max(m["ncc"][:2]) > 0.8  # the leading appearance modes follow the expression controls


def test_synthesizer_texture_equals_pca_of_regressor_output(synthetic):
    seq, tr, te, model, tex_tr = synthetic
    sadm = fit_sadm(model, seq, tr, tex_tr, "linear", {"ridge": 1.0}, SADMConfig(augment_copies=0))
    lm = seq.landmarks[te[:5]]
    syn = sadm.synthesizer()
    with torch.no_grad():
        tex = syn.texture(torch.from_numpy(lm)).reshape(5, -1).numpy()
    b = sadm.regressor.predict(sadm.features(lm))
    lim = 3 * np.sqrt(model.appearance_pca.eigenvalues)
    expect = model.texture_from_params(np.clip(b, -lim, lim))
    # each face part's deviation from the mean, scaled by its shrinkage weight
    w = sadm.region_shrink["weights"]
    assert set(w) == set(FACE_REGIONS) and all(0 <= v <= 1 for v in w.values())
    cols = np.concatenate([sum(reference_regions(model)[r] * w[r] for r in FACE_REGIONS)] * model.n_channels)
    expect = np.clip(model.appearance_pca.mean + cols * (expect - model.appearance_pca.mean), 0, 1)
    np.testing.assert_allclose(tex, expect, atol=1e-5)


def test_region_shrink_weights_closed_form(synthetic):
    """The least-squares weight of a part is 1 for a perfect prediction, 0.5 for one twice as
    far from the mean, 0 for one on the wrong side; the shrunk figure is never below the mean's."""
    _, _, _, model, tex_tr = synthetic
    true = np.clip(tex_tr[:6], 0, 1).astype(np.float64)
    mean = np.clip(model.appearance_pca.mean, 0, 1)
    parts = reference_regions(model)
    scale = np.concatenate([np.select([parts["eyes"], parts["mouth_interior"]], [2.0, -1.0], 1.0)] * model.n_channels)
    out = fit_weights(model, mean + scale * (true - mean), true)
    assert out["weights"]["eyes"] == pytest.approx(0.5, abs=1e-9)
    assert out["weights"]["mouth_interior"] == 0.0 and out["weights"]["rest"] == pytest.approx(1.0, abs=1e-9)
    for part, row in out["psnr"].items():
        assert row["shrunk"] >= row["mean_texture"] - 1e-9, part
    assert out["psnr"]["eyes"]["shrunk"] > 60  # halving a doubled deviation gives the truth back



def test_frame_regions_follow_the_mouth(synthetic):
    """In the reference frame, a closed-mouth frame's interior pixels are lips (as
    face_region_masks cuts the frame itself); open-mouth frames keep the reference's parts; the
    parts partition every frame's pixels."""
    from facesynth.landmarks import MOUTH_CLOSED, mouth_open

    seq, _, _, model, _ = synthetic
    lm = seq.landmarks
    closed = mouth_open(lm) <= MOUTH_CLOSED
    assert closed.any() and (~closed).any()  # the synthetic face opens and closes its mouth
    ref, parts = reference_regions(model), frame_regions(model, lm)
    assert set(parts) == set(ref) and ref["mouth_interior"].any()
    assert (sum(m.astype(int) for m in parts.values()) == 1).all()
    for name, m in parts.items():
        assert (m[~closed] == ref[name]).all()
    assert not parts["mouth_interior"][closed].any()
    assert (parts["lips"][closed] == (ref["lips"] | ref["mouth_interior"])).all()


def test_the_interior_weight_comes_from_open_mouths(synthetic):
    """A prediction exact everywhere but in closed mouths' interior pixels (far off there): with
    the frames' landmarks the interior keeps weight 1 (it is weighed where it is an interior)
    and the lips are untouched; without them the interior is shrunk."""
    from facesynth.landmarks import MOUTH_CLOSED, mouth_open

    seq, tr, _, model, tex_tr = synthetic
    lm = seq.landmarks[tr]
    closed = mouth_open(lm) <= MOUTH_CLOSED
    mean = np.clip(model.appearance_pca.mean, 0, 1)
    true = mean + 0.5 * (np.clip(tex_tr, 0, 1) - mean)
    pred = true.copy().reshape(len(tr), model.n_channels, -1)
    interior = reference_regions(model)["mouth_interior"]
    off = pred[closed][:, :, interior]
    pred[np.ix_(closed, np.arange(model.n_channels), np.flatnonzero(interior))] = 1.0 - off
    pred = pred.reshape(len(tr), -1)
    with_lm, without = fit_weights(model, pred, true, landmarks=lm), fit_weights(model, pred, true)
    assert with_lm["weights"]["mouth_interior"] == pytest.approx(1.0) and with_lm["weights"]["lips"] == pytest.approx(1.0)
    assert without["weights"]["mouth_interior"] < 0.9 and without["weights"]["lips"] == pytest.approx(1.0)
    # no open mouth at all: the interior has no weight (kept at 1 when applied)
    only_closed = fit_weights(model, pred[closed], true[closed], landmarks=lm[closed])
    assert "mouth_interior" not in only_closed["weights"] and "mouth_interior" not in only_closed["psnr"]

def test_region_shrink_blocked_cv_scores_every_frame_once_by_a_fit_without_it(synthetic):
    seq, tr, _, model, tex_tr = synthetic
    n = 23
    mean = np.clip(model.appearance_pca.mean, 0, 1)
    tex = mean + 0.1 * (np.clip(tex_tr[:n], 0, 1) - mean)  # doubled, still a convex mix: inside [0, 1]
    lm = seq.landmarks[tr[:n]].copy()
    lm[:, 0, 0] = np.arange(n)  # frame i's first landmark's x = i, to tell the frames apart
    seen = []

    class Doubling:  # predicts each frame twice as far from the mean as it is: every weight is 0.5
        def __init__(self, idx):
            self.idx = set(idx.tolist())

        def texture(self, lm_t):
            rows = lm_t[:, 0, 0].long().numpy()
            assert not self.idx & set(rows.tolist())  # never scored by a fit that saw it
            seen.extend(rows.tolist())
            return torch.from_numpy((mean + 2 * (tex[rows] - mean)).astype(np.float32))

    out = fit_region_shrink(Doubling, model, lm, tex, 5, 0)
    assert sorted(seen) == list(range(n)) and out["folds"] == 5 and out["val_frames"] == n
    assert all(w == pytest.approx(0.5, abs=1e-6) for w in out["weights"].values())
    seen.clear()
    out = fit_region_shrink(Doubling, model, lm, tex, 0, 6)  # the validation slice: the last 6 frames
    assert sorted(seen) == list(range(n - 6, n)) and out["folds"] == 0 and out["val_frames"] == 6


def test_region_shrink_off_is_the_plain_prediction(synthetic):
    seq, tr, te, model, tex_tr = synthetic
    sadm = fit_sadm(model, seq, tr, tex_tr, "linear", {"ridge": 1.0}, SADMConfig(augment_copies=0, region_shrink=False))
    assert sadm.region_shrink is None
    lm = seq.landmarks[te[:3]]
    with torch.no_grad():
        tex = sadm.synthesizer().texture(torch.from_numpy(lm)).reshape(3, -1).numpy()
    np.testing.assert_allclose(tex, np.clip(model.texture_from_params(sadm.predict_params(lm)), 0, 1), atol=1e-5)


def test_save_load_round_trip(synthetic, tmp_path):
    seq, tr, te, model, tex_tr = synthetic
    sadm = fit_sadm(model, seq, tr, tex_tr, "linear", {"ridge": 1.0})
    save_sadm(sadm, tmp_path)
    back = load_sadm(tmp_path)
    lm = torch.from_numpy(seq.landmarks[te[:4]])
    with torch.no_grad():
        a, b = sadm.synthesizer()(lm), back.synthesizer()(lm)
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y)


def _compose(overrides):
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def test_config_typos_fail_early():
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException):
        _compose(["model.referance_width=64"])
    with pytest.raises(ConfigCompositionException):
        _compose(["regressor.rigde=3"])


def test_train_defaults_are_what_train_py_composes():
    """Scripts calling fit_sadm directly get the Hydra defaults of train.py: the regressor's
    yaml hyper-parameters and the SADM settings it sets (krr: 1 px augmentation)."""
    from facesynth.runs.config import train_defaults

    name, params, sadm_cfg = train_defaults("krr")
    assert name == "krr" and params["kernel"] == "matern32" and params["alpha"] == 0.5
    assert sadm_cfg.augment_sigma == 1.0 and sadm_cfg.features == "landmarks"
    name, params, sadm_cfg = train_defaults("linear")
    assert name == "linear" and sadm_cfg.augment_sigma == 2.0


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_fit_sadm_defaults_are_train_py_defaults(name):
    """fit_sadm without a config trains with the SADM settings train.py composes for the
    regressor (the class's sadm_defaults and conf/regressor/NAME.yaml agree)."""
    from facesynth.runs.config import train_defaults

    assert SADMConfig(**REGISTRY[name].sadm_defaults) == train_defaults(name)[2]


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_composed_regressor_config_is_its_dataclass_defaults(name):
    """One source of defaults: train.py regressor=NAME trains with exactly the fields and
    values of the regressor's config dataclass (the yaml only selects it), and fit_sadm /
    make_config without parameters build the same config."""
    from dataclasses import asdict

    from facesynth.runs.config import train_defaults
    from facesynth.sadm.fit import make_config

    got_name, params, _ = train_defaults(name)
    want = asdict(REGISTRY[name].config_class())
    assert got_name == name
    assert {k: (list(v) if isinstance(v, tuple) else v) for k, v in want.items()} == params
    assert asdict(make_config(name, {})) == want


def test_run_directory_metrics_and_reevaluation(tmp_path):
    from facesynth.cli import main
    from facesynth.runs.training import run_training

    cfg = _compose(TINY)
    metrics = run_training(cfg, tmp_path / "run")
    on_disk = json.loads((tmp_path / "run" / "metrics.json").read_text())
    for key in ("regressor", "n_shape", "n_appearance", "train_frames", "test_frames", "psnr_ref", "psnr_frame", "psnr_train_ref", "ncc"):
        assert key in on_disk, key
    for key in ("psnr_ref", "psnr_frame", "psnr_train_ref"):
        assert set(on_disk[key]) >= {"sadm", "mean_texture", "oracle"}
        assert set(on_disk[key]["sadm"]) == {"0", "2"}
    assert "rewarp" in on_disk["psnr_frame"]
    assert len(on_disk["ncc"]) == on_disk["n_appearance"]
    assert on_disk["data"]["fingerprint"] and "torch" in on_disk["packages"] and on_disk["config"]["seed"] == 0
    for f in ("report.md", "config.yaml", "plots/psnr_vs_noise.png", "plots/ncc.png", "plots/error_map.png", "plots/test_grid.png"):
        assert (tmp_path / "run" / f).is_file(), f
    # re-evaluation of the saved run reproduces the reference-frame figures
    out = tmp_path / "re.json"
    assert main(["evaluate", str(tmp_path / "run"), "--noise", "0,2", "--no-frame", "--save-json", str(out)]) == 0
    again = json.loads(out.read_text())
    for row in ("sadm", "mean_texture", "oracle"):
        for k in ("0", "2"):
            assert again["psnr_ref"][row][k] == pytest.approx(metrics["psnr_ref"][row][k], abs=1e-6)
    # the run exports to ONNX (default: int8 basis, measured on the run's training landmarks)
    # and onnxruntime renders what torch renders with the same basis
    from facesynth.runtime import Renderer
    from facesynth.sadm.quantize import quantize_synthesizer

    assert main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "m.onnx")]) == 0
    r = Renderer(tmp_path / "m.onnx")
    assert r.metadata["appearance_basis"] == "int8" and float(r.metadata["quantization_psnr_vs_float_db"]) > 40
    sadm = load_sadm(tmp_path / "run")
    lm = make_synthetic_sequence(64, 192, seed=0).landmarks[-4:]
    crop, mask, place = r.render(lm)
    with torch.no_grad():
        t_crop, t_mask, t_place = quantize_synthesizer(sadm.synthesizer())[0](torch.from_numpy(lm))
    both = mask * t_mask.numpy()
    assert np.abs((crop - t_crop.numpy()) * both).max() <= 1e-4
    np.testing.assert_allclose(place, t_place.numpy(), atol=1e-3)


def test_sweep_writes_comparison_table(tmp_path):
    cmd = [sys.executable, str(ROOT / "train.py"), "-m", "regressor.ridge=1,100", *TINY,
           "eval.frame_level=false", "eval.train_level=false", f"hydra.sweep.dir={tmp_path}"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((tmp_path / "comparison.json").read_text())
    assert len(rows) == 2 and all("psnr_ref@0" in r for r in rows)
    md = (tmp_path / "comparison.md").read_text()
    assert md.count("\n") == 4 and "psnr_ref@0" in md


def test_train_reports_bad_data_path(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "train.py"), "data=video", f"data.path={tmp_path / 'nope'}",
                           f"hydra.run.dir={tmp_path / 'r'}"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "no such file or folder" in proc.stderr


def test_train_model_eri_uses_the_runs_temporal_split(tmp_path):
    """model=eri honours data.train_fraction and data.gap (no split of its own)."""
    from facesynth.runs.training import run_training

    cfg = _compose(["model=eri", "data.n_frames=40", "data.size=192", "eri.compare=[]", "eri.eval_frames=2",
                    "data.train_fraction=0.5", "data.gap=3"])
    metrics = run_training(cfg, tmp_path / "eri")
    assert (metrics["train_frames"], metrics["test_frames"]) == (20, 17)


def test_train_model_eri_through_hydra(tmp_path):
    """``train.py model=eri`` composes the eri/ group and writes the ERI run."""
    from facesynth.runs.training import run_training

    cfg = _compose(["model=eri", "data.n_frames=48", "data.size=192", "eri.compare=[]"])
    metrics = run_training(cfg, tmp_path / "eri")
    assert (tmp_path / "eri" / "eri_metrics.json").is_file() and (tmp_path / "eri" / "eri_report.md").is_file()
    assert metrics["config"]["variance"] == 0.97  # the eri/ group's defaults reached train_eri
    assert "kind: eri" in (tmp_path / "eri" / "config.yaml").read_text()


def test_rigid_landmark_features_closed_form_invariance_and_locality(synthetic):
    """``landmarks_rigid``: equals a numpy Umeyama fit on the rigid points applied to the frame
    landmarks; invariant to a similarity of the input; moving the mouth changes only the
    mouth's features (the 68-point Procrustes features change everywhere)."""
    from facesynth.geometry import apply_affine, similarity_fit
    from facesynth.sadm.synthesis import RIGID_POINTS, ShapeFeatures

    seq, tr, te, model, tex_tr = synthetic
    lm = seq.landmarks[te[:4]].astype(np.float64)
    mean = model.shape_pca.mean.reshape(-1, 2)
    r = list(RIGID_POINTS)
    want = apply_affine(lm, similarity_fit(lm[:, r], mean[r])).reshape(len(lm), -1) - model.shape_pca.mean
    want *= 100.0 / (mean[:, 0].max() - mean[:, 0].min())
    got = ShapeFeatures.numpy(model, lm.astype(np.float32), "landmarks_rigid")
    np.testing.assert_allclose(got, want, atol=2e-3)
    a, s = 0.3, 1.7
    moved = lm @ (s * np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])) + [40.0, -25.0]
    np.testing.assert_allclose(ShapeFeatures.numpy(model, moved.astype(np.float32), "landmarks_rigid"), got, atol=2e-3)
    opened = lm.copy()
    opened[:, 57:60, 1] += 6.0  # lower lip down
    opened[:, 65:68, 1] += 6.0
    for kind, others_fixed in (("landmarks_rigid", True), ("landmarks", False)):
        d = np.abs(ShapeFeatures.numpy(model, opened.astype(np.float32), kind)
                   - ShapeFeatures.numpy(model, lm.astype(np.float32), kind)).reshape(len(lm), 68, 2)
        mouth = list(range(57, 60)) + list(range(65, 68))
        rest = [i for i in range(68) if i not in mouth]
        assert d[:, mouth].max() > 1.0
        assert (d[:, rest].max() < 1e-3) == others_fixed
