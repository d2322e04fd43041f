"""Appearance compression for export (facesynth.sadm.compress): closed form, identity when
every component is kept, ONNX parity of the compressed model, recorded metadata, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _onnx_models import assert_export_matches, driving_landmarks, synthetic_model, synthetic_synthesizer

from facesynth.errors import FacesynthError
from facesynth.onnx.synthesis import export_run, export_synthesizer
from facesynth.rundir import save_run_synthesizer
from facesynth.sadm.compress import choose_components, compress_synthesizer, predicted_params

NAMES = ("linear", "poly2", "mlp", "svr")


def _texture(syn, lm):
    with torch.no_grad():
        return syn.texture(torch.from_numpy(lm)).double().numpy().reshape(len(lm), -1)


@pytest.mark.parametrize("name", NAMES)
def test_compressed_texture_is_the_closed_form(name):
    syn = synthetic_synthesizer(name)
    train = synthetic_model()[1]
    k_all = syn.appearance.components.shape[0]
    keep = max(k_all // 3, 1)
    small, info = compress_synthesizer(syn, train, keep=keep)
    b = predicted_params(syn, train)  # (N, K) clamped, from the *full* model
    idx = np.argsort(-b.var(0), kind="stable")[:keep]
    drop = np.setdiff1d(np.arange(k_all), idx)
    p = syn.appearance.components.double().numpy()
    mean2 = syn.appearance.mean.double().numpy() + b[:, drop].mean(0) @ p[drop]
    lm = driving_landmarks(seed=3, n=5)
    expect = np.clip(mean2 + predicted_params(syn, lm)[:, idx] @ p[idx], 0, 1)
    np.testing.assert_allclose(_texture(small, lm), expect, atol=2e-5)
    assert info["appearance_components"] == keep and info["appearance_components_full"] == k_all
    assert info["kept_components"] == idx.tolist()
    assert small.appearance.components.shape[0] == keep
    # the regressor itself predicts only the kept outputs (rows sliced, not a full prediction)
    with torch.no_grad():
        x = small.appearance.features(*small.encoder(torch.from_numpy(lm)))
        np.testing.assert_allclose(small.appearance.regressor(x).numpy(), syn.appearance.regressor(x).numpy()[:, idx],
                                   atol=1e-5)
    # the recorded PSNR is the compressed vs full texture PSNR over the given landmarks
    mse = np.mean((_texture(small, train) - _texture(syn, train)) ** 2)
    assert info["compression_psnr_vs_full_db"] == pytest.approx(10 * np.log10(1 / mse), abs=1e-6)


@pytest.mark.parametrize("name", ("linear", "mlp"))
def test_all_components_kept_is_the_full_model(name):
    syn = synthetic_synthesizer(name)
    train = synthetic_model()[1]
    full, info = compress_synthesizer(syn, train, keep=syn.appearance.components.shape[0])
    lm = driving_landmarks(seed=4, n=4)
    with torch.no_grad():
        a, b = syn(torch.from_numpy(lm)), full(torch.from_numpy(lm))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x.numpy(), y.numpy(), atol=1e-6)
    assert info["compression_psnr_vs_full_db"] > 120 and info["kept_predicted_variance"] == pytest.approx(1.0)
    # ... and the untouched original still has every component
    assert syn.appearance.components.shape[0] == info["appearance_components_full"]


def test_choose_components_by_count_and_variance():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(500, 5)) * np.array([1.0, 10.0, 0.1, 3.0, 0.01])
    assert choose_components(b, keep=2).tolist() == [1, 3]
    var = b.var(0)
    for q in (0.5, 0.9, 0.99, 0.99999, 1.0):
        idx = choose_components(b, predicted_variance=q)
        assert var[idx].sum() / var.sum() >= q - 1e-9  # enough ...
        assert var[idx[:-1]].sum() / var.sum() < q  # ... and the fewest
    for bad in ({"keep": 0}, {"keep": 6}, {"predicted_variance": 0.0}, {"predicted_variance": 1.5}, {},
                {"keep": 2, "predicted_variance": 0.9}):
        with pytest.raises(FacesynthError, match="appearance compression"):
            choose_components(b, **bad)


@pytest.mark.parametrize("name", ("linear", "svr"))
def test_compressed_export_matches_compressed_torch(name, tmp_path):
    syn = synthetic_synthesizer(name)
    small, _ = compress_synthesizer(syn, synthetic_model()[1], keep=2)
    path = export_synthesizer(small, tmp_path / "small.onnx")
    assert_export_matches(path, small, driving_landmarks(seed=7, n=4))


def test_export_run_records_compression(tmp_path):
    syn = synthetic_synthesizer("linear")
    model, train = synthetic_model()[:2]
    run = save_run_synthesizer(tmp_path / "run", model, syn.regressor_)
    k_all = syn.appearance.components.shape[0]
    path, small, meta = export_run(run, tmp_path / "c.onnx", components=2, landmarks=train)
    props = {p.key: p.value for p in __import__("onnx").load(str(path)).metadata_props}
    assert props["appearance_components"] == "2" and props["appearance_components_full"] == str(k_all)
    assert float(props["compression_psnr_vs_full_db"]) == pytest.approx(meta["compression_psnr_vs_full_db"])
    assert 10 < meta["compression_psnr_vs_full_db"] < 200
    # the default (40) keeps every component of this small model: no landmarks needed
    _, same, meta = export_run(run, tmp_path / "d.onnx")
    assert meta["compression"] == "none" and same.appearance.components.shape[0] == k_all
    # compression without the run's training landmarks (no config.yaml): a clear error
    with pytest.raises(FacesynthError, match="config.yaml: not found.*--landmarks"):
        export_run(run, tmp_path / "e.onnx", components=2)
    with pytest.raises(FacesynthError, match="2 finite landmark rows"):
        export_run(run, tmp_path / "e.onnx", components=2, landmarks=np.full((3, 68, 2), np.nan, np.float32))
    assert not (tmp_path / "e.onnx").exists()


def test_training_landmarks_from_run_config(tmp_path):
    from facesynth.data import temporal_split
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.rundir import training_landmarks

    (tmp_path / "config.yaml").write_text(
        "seed: 3\ndata:\n  kind: synthetic\n  path: null\n  n_frames: 12\n  size: 96\n  max_frames: null\n"
        "  train_fraction: 0.75\n  gap: 1\n"  # every data setting, as train.py writes them (read_config checks)
    )
    seq = make_synthetic_sequence(n_frames=12, size=96, seed=3)
    rows, _ = temporal_split(12, 0.75, 1)
    np.testing.assert_array_equal(training_landmarks(tmp_path), seq.landmarks[rows])


def test_sadm_compressed_is_compress_synthesizer():
    from facesynth.sadm.fit import SADM, SADMConfig

    syn = synthetic_synthesizer("linear")
    model, train = synthetic_model()[:2]
    sadm = SADM(model, syn.regressor_, "linear", SADMConfig(features="bs"))
    small, info = sadm.compressed(train, keep=2)
    ref, ref_info = compress_synthesizer(syn, train, keep=2)
    assert info == ref_info
    lm = driving_landmarks(seed=9, n=3)
    np.testing.assert_allclose(_texture(small, lm), _texture(ref, lm), atol=1e-6)
