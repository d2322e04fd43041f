"""Int8 appearance basis (facesynth.sadm.quantize): the quantizer's bounds, the integer
graph against a numpy closed form, ONNX Runtime parity for every regressor, the recorded
PSNR, the exported graph (MatMulInteger, 4x smaller basis) and its errors."""

from __future__ import annotations

import copy

import numpy as np
import onnx
import pytest
import torch
from _onnx_models import assert_export_matches, driving_landmarks, synthetic_model, synthetic_synthesizer

from facesynth.contract import CODE_LEVELS
from facesynth.errors import FacesynthError
from facesynth.onnx.synthesis import export_synthesizer, quantize_for_export
from facesynth.regressors import REGISTRY
from facesynth.sadm.compress import compress_synthesizer
from facesynth.sadm.quantize import Int8Basis, quantize_columns, quantize_synthesizer


def _texture(syn, lm):
    with torch.no_grad():
        return syn.texture(torch.from_numpy(lm)).double().numpy().reshape(len(lm), -1)


def test_quantize_columns_bounds():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(7, 50)) * rng.uniform(0.01, 3.0, size=50)
    w[:, 3] = 0.0
    codes, scale = quantize_columns(w)
    assert codes.dtype == np.int8 and scale.dtype == np.float32 and scale.shape == (50,)
    assert np.abs(codes).max() == CODE_LEVELS == 64 and codes.min() >= -CODE_LEVELS  # 7-bit: int16-safe pair sums
    assert (np.abs(codes).max(0)[np.arange(50) != 3] == CODE_LEVELS).all()  # every nonzero column uses the full range
    err = np.abs(codes * scale.astype(np.float64) - w)
    assert (err <= scale / 2 * (1 + 1e-6) + 1e-12).all()  # round to nearest: half a step at most
    assert (codes[:, 3] == 0).all() and scale[3] == 1.0
    for bad in (np.ones(5), np.full((2, 2), np.nan)):
        with pytest.raises(FacesynthError, match="int8 quantization"):
            quantize_columns(bad)
    with pytest.raises(FacesynthError, match=r"levels must be in \[1, 127\]"):
        quantize_columns(w, 128)
    codes8, _ = quantize_columns(w, 127)  # the 8-bit range of older files, still available for comparisons
    assert np.abs(codes8).max() == 127


def test_int8_basis_is_the_integer_closed_form():
    rng = np.random.default_rng(1)
    k, d = 6, 300
    comps = rng.normal(size=(k, d)) / np.sqrt(d)
    limit = rng.uniform(0.5, 4.0, size=k)
    basis = Int8Basis.from_basis(comps, limit)
    b = rng.uniform(-1, 1, size=(9, k)) * limit  # clamped coefficients
    b[0] = limit  # the clamp bounds themselves map to +-127
    b[1] = -limit
    with torch.no_grad():
        got = basis(torch.from_numpy(b.astype(np.float32))).double().numpy()
    a = np.rint(b.astype(np.float32) * basis.coef_scale.numpy())  # same float32 product as the graph
    assert np.abs(a).max() == 127
    codes, scale = basis.codes.numpy().astype(np.int64), basis.col_scale.numpy().astype(np.float64)
    expect = (a.astype(np.int64) @ codes) * scale  # exact integers, then the column scale
    np.testing.assert_allclose(got, expect, rtol=1e-6, atol=1e-9)
    # against the float basis: at most half a coefficient step plus half a code step per component
    exact = b @ comps
    step_a = limit / 127
    bound = (0.5 * step_a[:, None] * np.abs(comps)).sum(0) + 0.5 * (np.abs(b) / step_a[None] + 0.5).sum(1, keepdims=True) * scale
    assert (np.abs(got - exact) <= bound + 1e-7).all()
    np.testing.assert_allclose(basis.dequantized().numpy(), codes * scale / basis.coef_scale.numpy().astype(np.float64)[:, None])


def test_int8_basis_sums_exactly_beyond_float32_range():
    """With K > 1040 components the integer sums pass 2^24; torch sums them in float64."""
    k, d = 1100, 4
    basis = Int8Basis.from_basis(np.ones((k, d)), np.ones(k), levels=127)  # every code 127
    b = np.ones((1, k), np.float32)  # every coefficient code 127: sum 1100 * 127^2 > 2^24
    with torch.no_grad():
        got = basis(torch.from_numpy(b)).double().numpy()
    expect = k * 127 * 127 * basis.col_scale.numpy().astype(np.float64)
    np.testing.assert_allclose(got[0], expect, rtol=1e-7)
    assert k * 127 * 127 > 2**24


def test_int8_basis_needs_finite_limits():
    with pytest.raises(FacesynthError, match="finite, positive clamping limits.*--basis float32"):
        Int8Basis.from_basis(np.ones((2, 4)), np.array([1.0, np.inf]))


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_quantized_export_matches_quantized_torch(name, tmp_path):
    syn = synthetic_synthesizer(name)
    q, info = quantize_synthesizer(syn, synthetic_model()[1])
    path = export_synthesizer(q, tmp_path / "q.onnx")
    assert_export_matches(path, q, driving_landmarks(seed=11, n=5))
    # the file holds the int8 codes, not a float basis, and records the basis kind
    m = onnx.load(str(path))
    assert "MatMulInteger" in {n.op_type for n in m.graph.node}
    app = syn.appearance
    k, d = app.components.shape
    big = [i for i in m.graph.initializer if int(np.prod(i.dims)) == k * d]
    assert [i.data_type for i in big] == [onnx.TensorProto.INT8]
    props = {p.key: p.value for p in m.metadata_props}
    assert props["appearance_basis"] == "int8" and props["appearance_code_levels"] == str(CODE_LEVELS)
    assert info["appearance_basis_bytes"] == k * d


def test_recorded_psnr_and_the_float_model_is_untouched():
    syn = synthetic_synthesizer("linear")
    train = synthetic_model()[1]
    q, info = quantize_synthesizer(syn, train)
    mse = np.mean((_texture(q, train) - _texture(syn, train)) ** 2)
    assert info["quantization_psnr_vs_float_db"] == pytest.approx(10 * np.log10(1 / mse), abs=1e-6)
    assert info["quantization_psnr_vs_float_db"] > 45 and info["quantization_frames"] == len(train)
    assert syn.appearance.basis is None  # a copy: the float model is unchanged
    assert np.abs(_texture(q, train) - _texture(syn, train)).max() < 0.02


def test_quantize_errors_and_float_fallback():
    syn = synthetic_synthesizer("linear")
    train = synthetic_model()[1]
    q, _ = quantize_synthesizer(syn)
    with pytest.raises(FacesynthError, match="already quantized"):
        quantize_synthesizer(q)
    with pytest.raises(FacesynthError, match="compress before quantizing"):
        compress_synthesizer(q, train, keep=2)
    with pytest.raises(FacesynthError, match=r"landmarks must be \(N, 68, 2\), got \(68, 2\)"):
        quantize_synthesizer(syn, train[0])
    with pytest.raises(FacesynthError, match="appearance basis must be one of"):
        quantize_for_export(syn, train, "int4")
    same, info = quantize_for_export(syn, train, "float32")
    assert same is syn and info == {"appearance_basis": "float32"}
    # a model with clamping off has no coefficient range: the export keeps float32
    unclamped = copy.deepcopy(synthetic_synthesizer("linear"))  # the helper's models are shared: a copy
    unclamped.appearance.limit = torch.full_like(unclamped.appearance.limit, float("inf"))
    same, info = quantize_for_export(unclamped, train, "int8")
    assert same is unclamped and info["appearance_basis"] == "float32"
