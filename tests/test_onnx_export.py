"""ONNX export of the synthesis graph: parity with torch for every registered regressor
(synthetic and real landmarks), dynamic batch, metadata, run loading, CLI and Hydra entry."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from _onnx_models import driving_landmarks, exported, real_linear_synthesizer, synthetic_model, synthetic_synthesizer

from facesynth.errors import FacesynthError
from facesynth.onnx.synthesis import METADATA_KEYS, SynthesisGraph, export_run, export_synthesizer, torch_reference
from facesynth.regressors import REGISTRY
from facesynth.rundir import load_synthesizer, save_run_synthesizer
from facesynth.sadm.quantize import quantize_synthesizer

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def onnx_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("onnx")


def _ort(path):
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _assert_parity(path, syn, lm):
    """ONNX Runtime (one thread) against torch, by the int8 parity contract (float noise, plus
    one code step on each coefficient that the two round differently on a tie)."""
    crop, mask, place = _ort(path).run(None, {"landmarks": lm})
    (t_crop, t_mask, t_place), tol = torch_reference(syn, syn.appearance, path, {"landmarks": lm})
    assert crop.shape == t_crop.shape and mask.shape == t_mask.shape and place.shape == (len(lm), 2, 3)
    # masks may differ only where a pixel centre lies within float rounding of the face outline
    flips = (mask != t_mask)
    assert flips.mean() < 1e-4, f"{int(flips.sum())} mask pixels differ"
    per_frame = np.abs((crop - t_crop) * mask * t_mask).reshape(len(lm), -1).max(1)
    assert (per_frame <= tol).all(), (per_frame, tol)
    assert np.abs(place - t_place).max() <= 1e-3 * max(1.0, np.abs(t_place).max())
    return per_frame.max()


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_every_regressor_matches_torch(name, onnx_dir):
    syn = synthetic_synthesizer(name)
    path = exported(name, onnx_dir)
    lm = driving_landmarks(seed=3, n=5)
    _assert_parity(path, syn, lm)
    _assert_parity(path, syn, lm[:1])  # dynamic batch


def test_export_graph_equals_synthesizer():
    syn = synthetic_synthesizer("linear")
    lm = torch.from_numpy(driving_landmarks(seed=4, n=4))
    with torch.no_grad():
        ref, got = syn(lm), SynthesisGraph(syn)(lm)
    assert torch.equal(ref[1], got[1])
    assert (ref[0] - got[0]).abs().max() < 1e-4
    torch.testing.assert_close(ref[2], got[2], rtol=1e-5, atol=1e-3)


def test_metadata_opset_and_dynamic_axis(onnx_dir):
    path = exported("linear", onnx_dir)
    m = onnx.load(str(path))
    props = {p.key: p.value for p in m.metadata_props}
    assert set(METADATA_KEYS) <= set(props)
    assert props["landmark_scheme"] == "ibug68" and props["regressor"] == "linear"
    assert props["data_fingerprint"] == synthetic_model()[0].fingerprint
    assert json.loads(props["reference_size"]) == list(synthetic_model()[0].reference.size)
    assert [o.domain for o in m.opset_import if o.domain in ("", "ai.onnx")] and int(props["opset"]) == 18
    assert {o.version for o in m.opset_import if o.domain in ("", "ai.onnx")} == {18}
    dim = m.graph.input[0].type.tensor_type.shape.dim
    assert dim[0].dim_param and [d.dim_value for d in dim[1:]] == [68, 2]
    ops = {n.op_type for n in m.graph.node}
    assert not ops & {"Loop", "If", "Scan"} and all(n.domain in ("", "ai.onnx") for n in m.graph.node)


@pytest.mark.parametrize("basis", ["float32", "int8"])
def test_real_landmarks_match_torch(basis, shared_clip_dir, tmp_path):
    """A model fitted on lp_d6 frames, driven by lp_d6 landmarks it did not see (float32
    basis, and the int8 basis of the default export)."""
    from facesynth.data import load_sequence

    seq = load_sequence(shared_clip_dir("lp_d6"))
    syn = real_linear_synthesizer(seq, np.arange(0, 240, 6))
    if basis == "int8":
        syn = quantize_synthesizer(syn)[0]
    path = export_synthesizer(syn, tmp_path / "lp_d6.onnx")
    test_rows = np.arange(3, len(seq), 16)  # ~63 frames across the whole clip
    _assert_parity(path, syn, seq.landmarks[test_rows])


def test_run_round_trip_cli_and_errors(tmp_path):
    from facesynth.cli import main

    syn = synthetic_synthesizer("linear")
    run = save_run_synthesizer(tmp_path / "run", syn.face_model, syn.regressor_)
    loaded, meta = load_synthesizer(run)
    assert meta["regressor"] == "linear" and meta["data_fingerprint"] == syn.face_model.fingerprint
    lm = driving_landmarks(seed=5, n=3)
    path, exported_syn, meta = export_run(run, tmp_path / "a.onnx")  # the default export: int8 basis
    assert meta["appearance_basis"] == "int8" and exported_syn.appearance.basis is not None
    _assert_parity(path, exported_syn, lm)
    assert main(["export", str(run), "--out", str(tmp_path / "b.onnx")]) == 0
    _assert_parity(tmp_path / "b.onnx", quantize_synthesizer(loaded)[0], lm)
    assert main(["export", str(run), "--out", str(tmp_path / "f.onnx"), "--basis", "float32"]) == 0
    _assert_parity(tmp_path / "f.onnx", loaded, lm)
    assert "MatMulInteger" not in {n.op_type for n in onnx.load(str(tmp_path / "f.onnx")).graph.node}
    with pytest.raises(FacesynthError, match="not found"):
        load_synthesizer(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FacesynthError, match=r"not a training run \(sadm/sadm.json missing\)"):
        load_synthesizer(tmp_path / "empty")
    (run / "sadm" / "sadm.json").unlink()
    with pytest.raises(FacesynthError, match="not a training run"):
        load_synthesizer(run)
    assert main(["export", str(run), "--out", str(tmp_path / "c.onnx")]) == 2
    assert not (tmp_path / "c.onnx").exists()


def test_hydra_entry_point(tmp_path):
    syn = synthetic_synthesizer("linear")
    run = save_run_synthesizer(tmp_path / "run", syn.face_model, syn.regressor_)
    out = tmp_path / "h.onnx"
    res = subprocess.run([sys.executable, str(ROOT / "export" / "export.py"), f"run={run}", f"out={out}", "json=true"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    # the figure the export's own check (the int8 parity contract) measured and passed
    assert summary["regressor"] == "linear" and 0 <= summary["max_abs_diff_vs_torch"] < 1e-2
    assert summary["appearance_basis"] == "int8"
    _assert_parity(out, quantize_synthesizer(syn)[0], driving_landmarks(seed=6, n=2))


@pytest.mark.parametrize("features", ["landmarks", "landmarks_rigid"])
def test_landmark_feature_kinds_export_with_parity(features, tmp_path):
    """The landmark feature kinds (re-alignment on the rigid points included) trace to ONNX."""
    from facesynth.regressors import KRRRegressor
    from facesynth.sadm.synthesis import GlobalAppearance, ShapeFeatures, Synthesizer

    model, lm, _, y = synthetic_model()
    reg = KRRRegressor.fit(ShapeFeatures.numpy(model, lm, features), y)
    syn = Synthesizer(model, GlobalAppearance(model, reg, features)).eval()
    path = export_synthesizer(syn, tmp_path / f"{features}.onnx")
    _assert_parity(path, syn, driving_landmarks(seed=5, n=5))


def test_printed_summary_describes_the_bulky_avatar_metadata():
    from facesynth.onnx.export import brief

    meta = {"regressor": "linear", "avatar_neutral": [[1.0, 2.0]] * 68, "avatar_neutral_row": 3,
            "shape_pca": {"mean": [0.0] * 136, "components": [[0.0] * 136] * 2, "limit": [0.1, 0.2]}, "background_jpeg": "x" * 5000,
            "coverage_recording": {"z": [[0.0] * 8] * 7}}
    out = brief(meta)
    assert out == {"regressor": "linear", "avatar_neutral_row": 3, "shape_pca_components": 2, "background_jpeg_chars": 5000,
                   "coverage_recording_frames": 7}
