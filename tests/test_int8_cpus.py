"""The int8 appearance basis is exact on every CPU: x86 without VNNI adds pairs of u8 x s8
products in a saturating int16 (facesynth.ops), so exported codes must keep every pair sum
within int16.

* CPU-independent: the exported file's own codes, read back, bound every pair sum in int64
  (and the 8-bit codes of older files fail the same bound);
* this CPU: the file's MatMulInteger against int64 arithmetic on worst-case activations;
* an emulated AMD EPYC (AVX2, no VNNI; ``qemu-x86_64 -cpu EPYC-Rome``, Debian's qemu-user):
  the same probe, which must reproduce the saturation of 8-bit codes and be exact on ours;
* the runtime refuses a saturating file on such a CPU and warns about it on any other;
* export never names a file it has not checked, and a failed check names its cause.
"""

from __future__ import annotations

import logging
import os
import platform
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import onnx
import pytest
from _onnx_models import synthetic_model, synthetic_synthesizer

from facesynth.contract import CODE_LEVELS, CODE_LEVELS_KEY, INT16_MAX, LEGACY_CODE_LEVELS
from facesynth.errors import FacesynthError
from facesynth.onnx.int8check import (
    matmul_errors,
    matmul_integer_codes,
    pair_sum_worst,
    probe_model,
    reference,
    worst_activations,
)
from facesynth.onnx.synthesis import export_synthesizer
from facesynth.runtime import Renderer, cpu
from facesynth.sadm.quantize import quantize_synthesizer


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """{"new": default int8 export, "legacy": the same with 8-bit codes, "unrecorded": legacy
    without the code-range key (as files written before it existed)}."""
    d = tmp_path_factory.mktemp("int8")
    syn, train = synthetic_synthesizer("linear"), synthetic_model()[1]
    out = {}
    for name, levels in (("new", CODE_LEVELS), ("legacy", LEGACY_CODE_LEVELS)):
        q, info = quantize_synthesizer(syn, train, levels=levels)
        out[name] = export_synthesizer(q, d / f"{name}.onnx", info)
    m = onnx.load(str(out["legacy"]))
    keep = [p for p in m.metadata_props if p.key != CODE_LEVELS_KEY]
    del m.metadata_props[:]
    m.metadata_props.extend(keep)
    out["unrecorded"] = d / "unrecorded.onnx"
    onnx.save(m, str(out["unrecorded"]))
    return out


def test_exported_codes_cannot_saturate_on_any_cpu(files):
    codes = matmul_integer_codes(files["new"])
    assert codes.dtype == np.int8 and np.abs(codes.astype(np.int64)).max() == CODE_LEVELS
    assert pair_sum_worst(codes) <= INT16_MAX  # every column's two largest products, in int64
    assert Renderer(files["new"]).metadata[CODE_LEVELS_KEY] == CODE_LEVELS
    # the codes of files written before: the same bound fails (what x86 without VNNI got wrong)
    assert pair_sum_worst(matmul_integer_codes(files["legacy"])) > INT16_MAX


def test_pair_sum_worst_is_the_int64_closed_form():
    codes = np.array([[3, -64], [127, 64], [-5, -64]], np.int8)
    assert pair_sum_worst(codes) == 255 * (127 + 5)
    assert pair_sum_worst(np.full((1, 4), 64, np.int8)) == 255 * 64
    assert 2 * 255 * CODE_LEVELS <= INT16_MAX < 2 * 255 * (CODE_LEVELS + 1)  # 64 is the largest safe range


def test_matmul_integer_is_exact_on_this_cpu(files):
    codes = matmul_integer_codes(files["new"])
    a = worst_activations(codes.shape[0])
    assert a.dtype == np.uint8 and a.max() == 255 and a.min() == 1
    assert reference(codes, a)[0].tolist() == (127 * codes.astype(np.int64).sum(0)).tolist()
    assert matmul_errors(codes) == (0, 0)


PROBE = textwrap.dedent("""
    import sys
    import numpy as np
    import onnxruntime as ort
    sess = ort.InferenceSession(sys.argv[1], providers=["CPUExecutionProvider"])
    np.save(sys.argv[3], sess.run(None, {"a": np.load(sys.argv[2])})[0])
""")


@pytest.mark.skipif(platform.machine() != "x86_64" or shutil.which("qemu-x86_64") is None,
                    reason="needs an x86-64 host and qemu-user (apt-get install qemu-user; .ci/run installs it)")
def test_emulated_cpu_without_vnni(files, tmp_path):
    """ONNX Runtime under an emulated AMD EPYC Rome (AVX2, no AVX-512, no VNNI): the 8-bit
    codes of older files saturate there, the exported 7-bit codes are exact."""
    import onnxruntime

    site = os.path.dirname(os.path.dirname(onnxruntime.__file__))
    (tmp_path / "probe.py").write_text(PROBE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join({site, os.path.dirname(os.path.dirname(np.__file__))}),
           "OMP_NUM_THREADS": "1"}
    wrong = {}
    for name in ("new", "legacy"):
        codes = matmul_integer_codes(files[name])
        a = worst_activations(codes.shape[0])
        (tmp_path / f"{name}.onnx").write_bytes(probe_model(codes))
        np.save(tmp_path / f"{name}_a.npy", a)
        cmd = ["qemu-x86_64", "-cpu", "EPYC-Rome", os.path.realpath(sys.executable), "-S", str(tmp_path / "probe.py"),
               str(tmp_path / f"{name}.onnx"), str(tmp_path / f"{name}_a.npy"), str(tmp_path / f"{name}_y.npy")]
        run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
        got = np.load(tmp_path / f"{name}_y.npy").astype(np.int64)
        wrong[name] = int((got != reference(codes, a)).sum())
    assert wrong["legacy"] > 0  # the emulated CPU reproduces the saturation: the check below means something
    assert wrong["new"] == 0


def test_cpu_flags_and_vnni():
    text = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512_vnni\n\nprocessor\t: 1\nflags\t: fpu\n"
    assert cpu.cpu_flags(text) == {"fpu", "sse2", "avx2", "avx512f", "avx512_vnni"}
    assert cpu.cpu_flags("model name: x\n") == set()
    assert cpu.code_levels({"appearance_basis": "float32"}) is None
    assert cpu.code_levels({"appearance_basis": "int8"}) == LEGACY_CODE_LEVELS  # written before the key existed
    assert cpu.code_levels({"appearance_basis": "int8", CODE_LEVELS_KEY: 64}) == 64
    assert cpu.codes_can_saturate(LEGACY_CODE_LEVELS) and not cpu.codes_can_saturate(CODE_LEVELS)
    assert not cpu.codes_can_saturate(None)


@pytest.mark.parametrize("name", ["legacy", "unrecorded"])
def test_runtime_refuses_saturating_files_without_vnni_and_warns_elsewhere(files, name, monkeypatch, caplog):
    monkeypatch.setattr(cpu, "cpu_int8_saturates", lambda: True)
    with pytest.raises(FacesynthError, match=r"re-export it with this version \(facesynth export .* --out .*\): "
                                             r"this CPU has no VNNI") as exc:
        Renderer(files[name])
    assert "\n" not in str(exc.value) and str(files[name]) in str(exc.value)
    Renderer(files["new"])  # exact everywhere: loads
    monkeypatch.setattr(cpu, "cpu_int8_saturates", lambda: False)
    with caplog.at_level(logging.WARNING, logger="facesynth.runtime.cpu"):
        r = Renderer(files[name])
    assert r.render(synthetic_model()[1][:1])[0].shape[0] == 1
    assert any("renders right on this CPU, not on every CPU" in m for m in caplog.messages)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="facesynth.runtime.cpu"):
        Renderer(files["new"])
    assert not caplog.messages


def test_failed_export_check_names_out_cause_and_way_out(tmp_path, monkeypatch, caplog, capsys):
    from facesynth import cli
    from facesynth.onnx import synthesis
    from facesynth.runs.rundir import save_run_synthesizer

    syn = synthetic_synthesizer("linear")
    run = tmp_path / "run"
    save_run_synthesizer(run, syn.face_model, syn.regressor_)

    def broken(syn, path, landmarks=None, tol=1e-4):
        raise FacesynthError(f"{path}: ONNX Runtime differs from torch (max |crop diff| 3.1e-02, mask flips 0.00%)")

    monkeypatch.setattr(synthesis, "check_export", broken)
    out = tmp_path / "m.onnx"
    lm = tmp_path / "lm.npy"
    np.save(lm, synthetic_model()[1])
    with caplog.at_level(logging.INFO):
        code = cli.main(["export", str(run), "--out", str(out), "--landmarks", str(lm), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith(f"error: {out}: not written: ONNX Runtime differs from torch")
    assert "the int8 matmul is exact on this CPU" in err[0] and "--basis float32" in err[0]
    assert not out.exists() and list(tmp_path.glob("*.onnx*")) == []  # no half-written or temporary file
    assert not any("exported" in m for m in caplog.messages)
    # the float32 way out: no int8 cause, still names the file
    code = cli.main(["export", str(run), "--out", str(out), "--landmarks", str(lm), "--basis", "float32", "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith(f"error: {out}: not written:") and "int8" not in err


def test_successful_export_logs_after_the_check(tmp_path, caplog, capsys):
    from facesynth import cli
    from facesynth.runs.rundir import save_run_synthesizer

    syn = synthetic_synthesizer("linear")
    run = tmp_path / "run"
    save_run_synthesizer(run, syn.face_model, syn.regressor_)
    lm = tmp_path / "lm.npy"
    np.save(lm, synthetic_model()[1])
    out = tmp_path / "m.onnx"
    with caplog.at_level(logging.INFO):
        assert cli.main(["export", str(run), "--out", str(out), "--landmarks", str(lm)]) == 0
    msgs = caplog.messages
    exported = [i for i, m in enumerate(msgs) if m.startswith(f"exported {out}")]
    assert len(exported) == 1 and out.is_file()
    assert list(tmp_path.glob(".*onnx*")) == []
    capsys.readouterr()


def test_a_rounding_tie_moves_the_texture_by_at_most_one_code_step():
    """ORT and torch may round a coefficient on a tie differently (the regressors' float sums
    differ in the last bits): the export check's extra tolerance, max_step, bounds that."""
    import torch

    from facesynth.sadm.quantize import Int8Basis

    rng = np.random.default_rng(3)
    comps, limit = rng.normal(size=(5, 200)), rng.uniform(0.5, 2.0, 5)
    basis = Int8Basis.from_basis(comps, limit)
    steps = np.abs(basis.codes.numpy().astype(np.float64)) * basis.col_scale.numpy().astype(np.float64)
    assert basis.max_step() == pytest.approx(steps.max(), rel=1e-12)
    tie = (np.arange(5) - 2 + 0.5) / basis.coef_scale.numpy().astype(np.float64)  # every code on a .5 tie
    lo, hi = (torch.from_numpy(np.float32(tie * (1 + s * 1e-6))[None]) for s in (-1, 1))
    with torch.no_grad():
        diff = (basis(hi) - basis(lo)).abs().numpy()
    base = tie * (1 - 1e-6)
    for k in range(5):  # one flipped code at a time stays within one step
        one = base.copy()
        one[k] = tie[k] * (1 + 1e-6)
        with torch.no_grad():
            d = basis(torch.from_numpy(np.float32(one)[None])) - basis(torch.from_numpy(np.float32(base)[None]))
        assert 0 < float(d.abs().max()) <= basis.max_step() * (1 + 1e-6)
    assert float(diff.max()) > 0  # the ties did flip
