"""Issue 15, model files (rows 2, 6, 15): every file of a small run (face model + SADM) and
of an ERI model, corrupted every way (truncate, empty, garbage, delete, flip a bit, NaN,
wrong shape, bumped version, missing SHA-256, invalid JSON, missing field), loads as a
clean FacesynthError naming the file; the folders hold nothing else afterwards."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from _onnx_models import synthetic_synthesizer
from safetensors.numpy import load_file, save_file

from facesynth.artifact import _sha256
from facesynth.eri.model import EriModel
from facesynth.errors import FacesynthError
from facesynth.rundir import save_run_synthesizer
from facesynth.sadm.fit import load_sadm

RUN_FILES = ["face_model/face_model.safetensors", "face_model/face_model.json", "sadm/regressor.safetensors", "sadm/sadm.json"]
ERI_FILES = ["eri_model.safetensors", "eri_model.json"]
TENSOR_CORRUPTIONS = ["truncate", "empty", "garbage", "delete", "bitflip", "nan", "wrong_shape"]
JSON_CORRUPTIONS = ["truncate", "empty", "garbage", "delete", "bump_version", "no_sha", "wrong_sha", "drop_field",
                    "not_object"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    syn = synthetic_synthesizer("linear")
    d = tmp_path_factory.mktemp("run") / "run"
    save_run_synthesizer(d, syn.face_model, syn.regressor_, features="bs")
    load_sadm(d)  # the clean run loads
    return d


@pytest.fixture(scope="module")
def eri_dir(tmp_path_factory, model) -> Path:
    d = tmp_path_factory.mktemp("eri") / "eri"
    model.save(d)
    EriModel.load(d)
    return d


def _manifest_of(tensors: Path) -> Path:
    return next(p for p in tensors.parent.glob("*.json"))


def corrupt(path: Path, how: str, rng: np.random.Generator) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(bytes(rng.integers(0, 256, len(data), dtype=np.uint8)))
    elif how == "delete":
        path.unlink()
    elif how == "bitflip":
        b = bytearray(data)
        i = int(rng.integers(len(b) // 2, len(b)))  # in the tensor data, past the safetensors header
        b[i] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(b))
    elif how in ("nan", "wrong_shape"):  # rewritten with a consistent SHA-256: only the content check can catch it
        t = load_file(str(path))
        name = max((k for k in t if t[k].dtype.kind == "f"), key=lambda k: t[k].size)
        if how == "nan":
            t[name] = t[name].copy()
            t[name].reshape(-1)[len(t[name].reshape(-1)) // 2] = np.nan
        else:
            t[name] = np.ascontiguousarray(t[name].reshape(-1)[:-1])
        save_file(t, str(path))
        man = _manifest_of(path)
        m = json.loads(man.read_text())
        m["tensors_sha256"] = _sha256(path)
        man.write_text(json.dumps(m))
    else:
        m = json.loads(data)
        if how == "bump_version":
            m["format_version"] += 1
        elif how == "no_sha":
            del m["tensors_sha256"]
        elif how == "wrong_sha":
            m["tensors_sha256"] = "0" * 64
        elif how == "drop_field":
            drop = next(k for k in ("regressor_config", "config", "reference_size") if k in m)
            del m[drop]
        elif how == "not_object":
            m = [m]
        path.write_text(json.dumps(m))


def _cases(files):
    return [(f, how) for f in files for how in (TENSOR_CORRUPTIONS if f.endswith(".safetensors") else JSON_CORRUPTIONS)]


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


@pytest.mark.parametrize("rel, how", _cases(RUN_FILES))
def test_corrupt_run_file_is_a_clean_error(run_dir, tmp_path, rel, how):
    d = _copy(run_dir, tmp_path / "run")
    before = sorted(str(p.relative_to(d)) for p in d.rglob("*"))
    corrupt(d / rel, how, np.random.default_rng(len(rel) * 31 + len(how)))
    with pytest.raises(FacesynthError) as exc:
        load_sadm(d)
    msg = str(exc.value)
    assert "\n" not in msg and Path(rel).parent.name in msg  # one line naming the folder/file
    after = sorted(str(p.relative_to(d)) for p in d.rglob("*"))
    assert after == [p for p in before if not (how == "delete" and p == rel)]  # nothing added, nothing hidden


@pytest.mark.parametrize("rel, how", _cases(ERI_FILES))
def test_corrupt_eri_file_is_a_clean_error(eri_dir, tmp_path, rel, how):
    d = _copy(eri_dir, tmp_path / "eri")
    corrupt(d / rel, how, np.random.default_rng(len(rel) * 17 + len(how)))
    with pytest.raises(FacesynthError) as exc:
        EriModel.load(d)
    assert "\n" not in str(exc.value) and "eri" in str(exc.value)


def test_row2_face_model_of_another_save_is_refused(run_dir, tmp_path):
    """The SADM manifest records the face model's SHA-256: a face_model/ from another
    (here: re-saved, valid) model does not pair with it."""
    from facesynth.model.artifact import save_face_model
    from facesynth.sadm.fit import load_sadm as load

    d = _copy(run_dir, tmp_path / "run")
    model = load(d).model
    model.appearance_pca.mean = model.appearance_pca.mean * 0.5
    save_face_model(model, d / "face_model")
    with pytest.raises(FacesynthError, match="not the face model this SADM was saved with"):
        load(d)


def test_row6_flipped_exponent_bit_is_caught(run_dir, tmp_path):
    """A single flipped exponent bit of a float in appearance_mean: refused (SHA-256)."""
    d = _copy(run_dir, tmp_path / "run")
    path = d / "face_model" / "face_model.safetensors"
    b = bytearray(path.read_bytes())
    header = 8 + int.from_bytes(b[:8], "little")
    info = json.loads(b[8:header])["appearance_mean"]
    start = header + info["data_offsets"][0]
    b[start + 3] ^= 0x40  # float32 little-endian: byte 3 holds the sign and the high exponent bits
    path.write_bytes(bytes(b))
    with pytest.raises(FacesynthError, match="altered or corrupt"):
        load_sadm(d)


def test_row15_tensor_files_get_the_permissions_of_the_json(run_dir):
    for sub in ("face_model", "sadm"):
        modes = {p.suffix: stat.S_IMODE(os.stat(p).st_mode) for p in (run_dir / sub).iterdir()}
        assert modes[".safetensors"] == modes[".json"], modes
        assert modes[".json"] == 0o666 & ~_umask()


def _umask() -> int:
    u = os.umask(0)
    os.umask(u)
    return u


def test_row6_export_of_a_nan_model_fails_cleanly_and_writes_nothing(run_dir, tmp_path, capsys):
    from facesynth.cli import main

    d = _copy(run_dir, tmp_path / "run")
    corrupt(d / "face_model" / "face_model.safetensors", "nan", np.random.default_rng(0))
    out = tmp_path / "out"
    out.mkdir()
    assert main(["export", str(d), "--out", str(out / "m.onnx"), "--components", "0"]) == 2
    err = capsys.readouterr().err
    assert "NaN or infinite" in err and "face_model.safetensors" in err and err.count("\n") == 1
    assert sorted(out.iterdir()) == []
