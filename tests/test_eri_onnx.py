"""ONNX export of ERI synthesis (FAPs + target neutral face -> rendered face): ONNX Runtime
vs EriSynthesizer's torch path on synthetic and real (lp_d6 -> lp_d10) data, every SVR
variant, raw ratios, frames, metadata, the exact FAP Jacobian, the runtime's input
checks, and ``facesynth export RUN --target``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import onnx
import pytest
import torch

from facesynth.cli import main
from facesynth.eri.config import EriConfig
from facesynth.eri.driving import VARIANTS
from facesynth.eri.faps import N_FAPS, fap_displacements, faps_to_landmarks
from facesynth.eri.model import EriModel
from facesynth.eri.synthesis import EriSynthesizer
from facesynth.errors import FacesynthError
from facesynth.onnx.eri import METADATA_KEYS, EriGraph, export_eri, torch_reference
from facesynth.runtime import EriRenderer, Renderer, read_metadata
from tests._eri import CFG, _sequence


@pytest.fixture(scope="module")
def target():
    """Another 'person': a different smooth image, landmarks scaled, rotated and moved."""
    other = _sequence(12, seed=5)
    lm = other.landmarks[0].astype(np.float64)
    c = lm.mean(0)
    a = 0.08
    rot = 1.1 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return other.frame(0), ((lm - c) @ rot.T + c + [4.0, -3.0]).astype(np.float32)


@pytest.fixture(scope="module")
def onnx_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("eri_onnx")


def _faps(seq, model, rng_seed=0):
    """Measured FAPs of unseen frames, plus random ones of the same spread (B = 8)."""
    f = model.faps(seq.landmarks[10:16])
    rng = np.random.default_rng(rng_seed)
    return np.concatenate([f, rng.normal(0, 1, (2, N_FAPS)) * f.std(0) + f.mean(0)]).astype(np.float32)


def assert_parity(renderer, syn, faps, tol=1e-4):
    crop, mask, place = renderer.render(faps, copy=True)
    t_crop, t_mask, t_place = torch_reference(syn, faps)
    assert crop.shape == t_crop.shape and mask.shape == t_mask.shape and place.shape == (len(faps), 2, 3)
    flips = mask != t_mask  # only pixel centres within float rounding of the face outline may differ
    assert flips.mean() < 1e-4, f"{int(flips.sum())} mask pixels differ"
    assert mask.sum() > 1000
    diff = float(np.abs((crop - t_crop) * mask * t_mask).max())
    assert diff <= tol
    assert np.abs(place - t_place).max() <= 1e-3 * max(1.0, np.abs(t_place).max())
    return diff


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_variant_matches_torch(variant, seq, model, target, onnx_dir):
    syn = EriSynthesizer(model, *target, variant=variant)
    path = export_eri(syn, onnx_dir / f"{variant}.onnx")
    r = EriRenderer(path)
    faps = _faps(seq, model)
    assert_parity(r, syn, faps)
    assert_parity(r, syn, faps[3:4])  # dynamic batch
    assert r.metadata["driver"] == variant and r.metadata["support_vectors"] == len(model.regressors[variant].sv)


def test_raw_ratios_and_plain_ratio_models(seq, target, onnx_dir):
    plain = EriModel.fit(seq, np.arange(12), EriConfig(**{**CFG, "log": False, "edge_tau": 0.05}))
    for m, raw in ((plain, False), (plain, True)):
        syn = EriSynthesizer(m, *target, raw=raw)
        r = EriRenderer(export_eri(syn, onnx_dir / f"plain_{raw}.onnx"))
        assert r.metadata["raw_ratios"] is raw
        assert_parity(r, syn, _faps(seq, m, 1))


def test_graph_equals_synthesizer_in_torch(seq, model, target):
    syn = EriSynthesizer(model, *target)
    faps = _faps(seq, model)
    with torch.no_grad():
        got = [t.numpy() for t in EriGraph(syn)(torch.from_numpy(faps))]
    want = torch_reference(syn, faps)
    assert np.array_equal(got[1], want[1])
    assert np.abs((got[0] - want[0]) * got[1]).max() < 1e-4
    np.testing.assert_allclose(got[2], want[2], rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(syn.textures(faps).numpy(), EriGraph(syn).textures(torch.from_numpy(faps)).numpy(),
                               atol=1e-5)
    for v in VARIANTS:  # the kernel expansion over distinct support vectors = the bank's predictions
        g = EriGraph(EriSynthesizer(model, *target, variant=v))
        assert g.n_distinct <= 12 < g.n_support_vectors  # 12 training rows shared by the K machines
        want = model.predict_coefficients(faps, v, clamp=False)
        got = g.coefficients(torch.from_numpy(faps)).numpy()
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * np.abs(want).max())


def test_fap_to_landmark_map_is_linear(model, target):
    """The export's premise: faps_to_landmarks = neutral + J f with J from the identity."""
    neutral = target[1]
    jac = fap_displacements(neutral, np.eye(N_FAPS)).reshape(N_FAPS, 136)
    f = np.random.default_rng(2).normal(0, 80, (5, N_FAPS))
    np.testing.assert_allclose(fap_displacements(neutral, f).reshape(5, 136), f @ jac, atol=1e-9)
    np.testing.assert_allclose(faps_to_landmarks(neutral, f).reshape(5, 136), neutral.reshape(1, 136) + f @ jac, atol=1e-4)


def test_frames_match_the_torch_renderer(seq, model, target, onnx_dir):
    syn = EriSynthesizer(model, *target)
    r = EriRenderer(export_eri(syn, onnx_dir / "frames.onnx"))
    faps = _faps(seq, model)
    want, _ = syn.render(faps)
    got = r.render_frames(faps, target[0])
    assert got.shape == want.shape and got.dtype == np.uint8
    diff = np.abs(got.astype(int) - want)
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3  # same compositing; crops within 1e-4 -> rounding only
    backgrounds = np.stack([seq.frame(i) for i in range(len(faps))])
    want_bg, _ = syn.render(faps, backgrounds=backgrounds)
    assert np.abs(r.render_frames(faps, backgrounds).astype(int) - want_bg).max() <= 1


def test_metadata_and_graph(model, target, onnx_dir):
    syn = EriSynthesizer(model, *target)
    path = export_eri(syn, onnx_dir / "meta.onnx", {"run": "unit"})
    m = onnx.load(str(path))
    props = read_metadata(path)
    assert set(METADATA_KEYS) <= set(props)
    assert props["kind"] == "eri" and props["driver"] == model.driver and props["n_faps"] == N_FAPS
    assert props["data_fingerprint"] == model.fingerprint and props["run"] == "unit"
    assert props["frame_size"] == [target[0].shape[1], target[0].shape[0]] and props["reference_size"] == list(model.reference.size)
    assert props["canvas_size"] == list(syn.canvas) and len(props["target_fingerprint"]) == 16
    assert {o.version for o in m.opset_import if o.domain in ("", "ai.onnx")} == {18}
    dim = m.graph.input[0].type.tensor_type.shape.dim
    assert m.graph.input[0].name == "faps" and dim[0].dim_param and dim[1].dim_value == N_FAPS
    assert not {n.op_type for n in m.graph.node} & {"Loop", "If", "Scan"}
    assert all(n.domain in ("", "ai.onnx") for n in m.graph.node)


def test_runtime_checks_inputs_and_formats(model, target, onnx_dir, tmp_path):
    syn = EriSynthesizer(model, *target)
    path = export_eri(syn, onnx_dir / "checks.onnx")
    r = EriRenderer(path)
    with pytest.raises(FacesynthError, match=r"shape \(B, 36\)"):
        r.render(np.zeros((2, 35), np.float32))
    with pytest.raises(FacesynthError, match="NaN"):
        r.render(np.full((1, 36), np.nan, np.float32))
    with pytest.raises(FacesynthError, match="dtype"):
        r.render(np.array([["a"] * 36]))
    assert r.render(np.zeros(36))[0].shape[0] == 1  # one (36,) vector, any real dtype
    with pytest.raises(FacesynthError, match="target's frame size"):
        r.render_frames(np.zeros((1, 36)), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(FacesynthError, match="use facesynth.runtime.EriRenderer"):
        Renderer(path)
    from _onnx_models import exported

    with pytest.raises(FacesynthError, match="use facesynth.runtime.Renderer"):
        EriRenderer(exported("linear", tmp_path))


def test_export_cli(seq, model, target, tmp_path, capsys):
    model.save(tmp_path / "run" / "eri")
    cv2.imwrite(str(tmp_path / "b.png"), cv2.cvtColor(target[0], cv2.COLOR_RGB2BGR))
    np.save(tmp_path / "b.npy", target[1][None])
    args = ["export", str(tmp_path / "run"), "--out", str(tmp_path / "e.onnx"), "--target", str(tmp_path / "b.png"),
            "--target-landmarks", str(tmp_path / "b.npy"), "--variant", "nu_linear", "--json"]
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out.strip())
    assert summary["max_abs_diff_vs_torch"] <= 1e-4 and summary["driver"] == "nu_linear"
    syn = EriSynthesizer(EriModel.load(tmp_path / "run"), *target, variant="nu_linear")
    assert_parity(EriRenderer(tmp_path / "e.onnx"), syn, _faps(seq, model))
    # a run without an ERI model, a missing target, an ERI run without --target: clear errors, no file
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), "--out", str(tmp_path / "x.onnx")] + args[4:]) == 2
    assert "no ERI model" in capsys.readouterr().err
    assert main(args[:4] + ["--target", str(tmp_path / "nope.png")]) == 2
    assert "no such target" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "y.onnx")]) == 2
    assert "pass --target" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists() and not (tmp_path / "y.onnx").exists()


def test_real_lp_d6_model_on_lp_d10_matches_torch(shared_clip_dir, tmp_path):
    """A small ERI model trained on lp_d6, the lp_d10 subject as target, driven by FAPs of
    lp_d6 frames it did not see."""
    from facesynth.data import load_sequence
    from facesynth.eri.faps import compute_faps
    from facesynth.eri.geometry import select_neutral

    seq = load_sequence(shared_clip_dir("lp_d6"))
    tgt = load_sequence(shared_clip_dir("lp_d10"))
    model = EriModel.fit(seq, np.arange(0, 600, 15), EriConfig(width=96, compare=[], batch_size=8))
    row = select_neutral(tgt.landmarks)[0]
    test_rows = np.arange(620, len(seq), 24)  # ~16 unseen frames
    faps = compute_faps(seq.landmarks[test_rows], model.neutral_landmarks)
    for raw in (False, True):
        syn = EriSynthesizer(model, tgt.frame(row), tgt.landmarks[row], raw=raw)
        r = EriRenderer(export_eri(syn, tmp_path / f"lp_d6_{raw}.onnx"))
        assert_parity(r, syn, faps)
    want, _ = syn.render(faps[:4])
    diff = np.abs(r.render_frames(faps[:4], tgt.frame(row)).astype(int) - want).max(-1)
    # crops within 1e-4; the seam is composited in a window round each crop, whose placement
    # (ONNX Runtime's vs torch's) can move it by a pixel: OpenCV's 1/32-pixel warp grid then
    # rounds a few edge pixels differently (measured: 2 of 4 x 512 x 512 pixels by 2)
    assert diff.max() <= 2 and (diff > 1).sum() <= 10


def test_hydra_entry_point_exports_eri(seq, model, target, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    model.save(tmp_path / "run" / "eri")
    cv2.imwrite(str(tmp_path / "b.png"), cv2.cvtColor(target[0], cv2.COLOR_RGB2BGR))
    np.save(tmp_path / "b.npy", target[1][None])
    script = Path(__file__).resolve().parents[1] / "export" / "export.py"
    res = subprocess.run([sys.executable, str(script), f"run={tmp_path / 'run'}", f"out={tmp_path / 'h.onnx'}",
                          f"target={tmp_path / 'b.png'}", f"target_landmarks={tmp_path / 'b.npy'}", "raw_ratios=true", "json=true"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["max_abs_diff_vs_torch"] <= 1e-4 and summary["raw_ratios"] is True
    assert_parity(EriRenderer(tmp_path / "h.onnx"), EriSynthesizer(model, *target, raw=True), _faps(seq, model))
