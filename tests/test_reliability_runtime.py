"""Issue 15, runtime and export (rows 5, 6, 9, 10): landmark ranges and frame bounds,
non-finite models and outputs, tampered metadata, export options checked before work."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from _onnx_models import driving_landmarks, exported

from facesynth.cli import main
from facesynth.errors import FacesynthError
from facesynth.runtime import Renderer


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return exported("linear", tmp_path_factory.mktemp("onnx"))


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def _tampered(src: Path, dst: Path, meta: dict | None = None, nan: bool = False) -> Path:
    m = onnx.load(str(src))
    for k, v in (meta or {}).items():
        for p in m.metadata_props:
            if p.key == k:
                p.value = v
    if nan:  # NaN into the largest float initializer (the appearance basis or mean)
        init = max((i for i in m.graph.initializer if i.data_type == onnx.TensorProto.FLOAT),
                   key=lambda i: int(np.prod(i.dims)))
        arr = onnx.numpy_helper.to_array(init).copy()
        arr.reshape(-1)[::7] = np.nan
        init.CopyFrom(onnx.numpy_helper.from_array(arr, init.name))
    onnx.save(m, str(dst))
    return dst


@pytest.mark.parametrize("shift, scale", [(1e9, 1.0), (0.0, 1e20), (0.0, -1e6)])
def test_row10_far_landmarks_are_refused(model_path, shift, scale):
    r = Renderer(model_path)
    lm = driving_landmarks(seed=1, n=2) * scale + shift
    with pytest.raises(FacesynthError, match=r"landmarks: coordinates beyond"):
        r.render(lm)


def test_row10_ragged_list_and_tampered_metadata(model_path, tmp_path):
    r = Renderer(model_path)
    with pytest.raises(FacesynthError, match="landmarks: not a rectangular array"):
        r.render([[[1.0, 2.0]] * 68, [[1.0, 2.0]] * 67])
    for key, value, needle in [("canvas_size", '"big"', "canvas_size"), ("canvas_size", "[1e9, 3]", "canvas_size"),
                               ("channels", "7", "channels")]:
        bad = _tampered(model_path, tmp_path / f"bad_{key}.onnx", {key: value})
        if key == "canvas_size" and not any(p.key == key for p in onnx.load(str(bad)).metadata_props):
            continue
        with pytest.raises(FacesynthError, match=needle):
            Renderer(bad)


def test_row6_nan_model_is_refused_by_renderer_and_app(model_path, tmp_path, capsys):
    bad = _tampered(model_path, tmp_path / "nan.onnx", nan=True)
    with pytest.raises(FacesynthError, match="not finite"):
        Renderer(bad).render(driving_landmarks(seed=2, n=1))
    np.save(tmp_path / "lm.npy", driving_landmarks(seed=2, n=3))
    out = tmp_path / "out" / "v.mp4"
    assert main(["app", "--model", str(bad), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(out),
                 "--no-progress"]) == 2
    assert "not finite" in capsys.readouterr().err
    assert not out.parent.exists()  # no video, no hidden temp, not even the folder the write made


@pytest.mark.parametrize("case", ["all_far", "one_outlier", "outlier_with_size"])
def test_row5_app_refuses_far_landmarks_before_rendering(model_path, tmp_path, case, capsys):
    lm = driving_landmarks(seed=3, n=4)
    extra = []
    if case == "all_far":
        lm = lm + 1e9
    elif case == "one_outlier":
        lm[2] += 30000.0
    else:
        lm[1] += 3000.0
        extra = ["--size", "240x240"]
    np.save(tmp_path / "lm.npy", lm)
    out = tmp_path / "o" / "v.mp4"
    assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(out),
                 "--no-progress", *extra]) == 2
    err = capsys.readouterr().err
    assert (err.startswith("error: landmarks") or "lm.npy" in err) and err.count("\n") == 1
    assert not out.parent.exists()  # refused before anything was written, not even the folder


def test_row9_export_options_are_checked_before_loading(tmp_path, capsys):
    run = tmp_path / "no_such_run"  # never read: the options fail first
    assert main(["export", str(run), "--out", str(tmp_path / "m.onnx"), "--opset", "5"]) == 2
    assert "--opset" in capsys.readouterr().err
    (tmp_path / "folder").mkdir()
    assert main(["export", str(run), "--out", str(tmp_path / "folder")]) == 2
    assert "existing folder" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert main(["export", str(run), "--out", str(tmp_path / "afile" / "m.onnx")]) == 2
    assert "afile" in capsys.readouterr().err
    assert _listing(tmp_path) == ["afile", "folder"]


def test_row6_export_summary_is_strict_json(capsys):
    from facesynth.progress import json_line, result

    assert json.loads(json_line({"a": 1.5})) == {"a": 1.5}
    with pytest.raises(FacesynthError, match="non-finite"):
        json_line({"max_abs_diff_vs_torch": float("nan")})
    with pytest.raises(FacesynthError, match="non-finite"):  # the line for people is refused too
        result("wrote m.onnx", {"max_abs_diff_vs_torch": float("nan")})
    assert capsys.readouterr().out == ""


APP_UNDER_SIGTERM = """
import sys
import facesynth.runtime.pipeline as pipeline
real = pipeline.render_frames

def slow(*a, **k):  # one real frame, then wait for the parent's signal (mid-write)
    for frame in real(*a, **k):
        yield frame
        print("ready", flush=True)
        sys.stdin.read()

pipeline.render_frames = slow
from facesynth.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_row11_sigterm_during_app_leaves_nothing(model_path, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    np.save(tmp_path / "lm.npy", driving_landmarks(seed=4, n=3))
    out = tmp_path / "out"
    out.mkdir()
    p = subprocess.Popen([sys.executable, "-c", APP_UNDER_SIGTERM, "app", "--model", str(model_path), "--landmarks",
                          str(tmp_path / "lm.npy"), "--out", str(out / "v.mp4"), "--no-progress"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=root,
                         env={**os.environ, "PYTHONPATH": str(root)})
    assert p.stdout.readline().strip() == "ready"
    assert len(_listing(out)) == 1 and _listing(out)[0].startswith(".v.mp4.facesynth-tmp-")  # mid-write
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143 and "terminated" in err
    assert _listing(out) == []
