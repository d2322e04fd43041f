"""The live page's Python side without a browser: ``facesynth web build`` / ``serve`` refuse what
is not an avatar in one line, the built folder holds what the page loads, the server sends the
headers WebAssembly threads need, and the landmark tables equal the project's own."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from _page import require_page

from facesynth.cli import main
from facesynth.contract import SYNTHESIS_FORMAT, TALKING_HEAD_FORMAT
from facesynth.web import site


def _tiny_onnx(path, metadata: dict) -> None:
    import onnx
    from onnx import TensorProto, helper

    w = helper.make_tensor("w", TensorProto.FLOAT, [1, 2000], np.arange(2000, dtype=np.float32) / 7)  # a weight to split
    g = helper.make_graph([helper.make_node("Add", ["x", "w"], ["y"])], "g", [helper.make_tensor_value_info(
        "x", TensorProto.FLOAT, [1, 1])], [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2000])], [w])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])
    helper.set_model_props(m, {k: json.dumps(v) for k, v in metadata.items()})
    onnx.save(m, str(path))


def _site_avatar(tmp_path):
    """A real talking-head file (the synthetic subject's, ~5 s: ``serve`` and ``web build`` check
    it) for building the page; skips without what the page needs (the tflite parser and
    MediaPipe for the tracker, onnxruntime-web from ``facesynth web setup``)."""
    from _onnx_models import synthetic_talking_head

    require_page()
    return synthetic_talking_head(tmp_path)


@pytest.mark.parametrize("command", [["web", "build"], ["serve"]])
def test_without_the_npm_packages_is_one_line_naming_setup(tmp_path, capsys, monkeypatch, command):
    model = tmp_path / "avatar.onnx"
    _tiny_onnx(model, {"format": TALKING_HEAD_FORMAT, "landmark_scheme": "ibug68"})
    monkeypatch.setattr(site, "npm_roots", lambda: [tmp_path / "page", tmp_path / "cache"])
    out = [str(tmp_path / "site")] if command[0] == "web" else ["--port", "0"]
    assert main([*command, str(model), *out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "facesynth web setup" in err, err
    assert not (tmp_path / "site").exists()


def test_page_files_are_package_data():
    """The page and its npm manifest ship in the wheel (pyproject's package-data lists them)."""
    import tomllib

    data = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    listed = data["tool"]["setuptools"]["package-data"]["facesynth"]
    for f in (*site.PAGE_FILES, *site.NPM_FILES):
        assert (site.PAGE / f).is_file(), f
        assert any(Path("web/page", f).match(p) for p in listed), f


@pytest.mark.parametrize("command", [["web", "build"], ["serve"]])
def test_not_an_avatar_is_one_line(tmp_path, capsys, command):
    model = tmp_path / "other.onnx"
    _tiny_onnx(model, {"producer": "someone else"})
    out = [str(tmp_path / "site")] if command[0] == "web" else ["--port", "0"]
    assert main([*command, str(model), *out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a facesynth avatar" in err[0] and "other.onnx" in err[0]
    assert not (tmp_path / "site").exists()
    assert main([*command, str(tmp_path / "missing.onnx"), *out]) == 2
    assert "no such model file" in capsys.readouterr().err
    _tiny_onnx(model, {"format": SYNTHESIS_FORMAT, "landmark_scheme": "ibug68"})  # a face model: named, with the export
    assert main([*command, str(model), *out]) == 2
    err = capsys.readouterr().err.strip()
    assert "a face model, not a talking head" in err and "--talking-head" in err and not (tmp_path / "site").exists()


def test_schemes_json_equals_the_landmark_tables():
    from facesynth.landmarks import get_scheme

    tables = site.schemes_json()
    rng = np.random.default_rng(0)
    for name, t in tables.items():
        s = get_scheme(name)
        pts = rng.random((s.n_points, 2)).astype(np.float32) * 100
        mapped = np.array([sum(w * pts[j] for j, w in row) for row in t["to_ibug68"]])
        np.testing.assert_allclose(mapped, s.to_ibug68(pts), atol=1e-3)
        assert t["n_points"] == s.n_points


def test_server_headers_and_types(tmp_path):
    (tmp_path / "a.wasm").write_bytes(b"\0asm")
    (tmp_path / "b.mjs").write_text("export {}")
    from bench.browser import served

    with served(tmp_path) as url:
        assert url.startswith("http://127.0.0.1:")
        for name, mime in (("a.wasm", "application/wasm"), ("b.mjs", "text/javascript")):
            with urllib.request.urlopen(url + name) as r:
                assert r.headers["Content-Type"].split(";")[0] == mime
                assert r.headers["Cross-Origin-Opener-Policy"] == "same-origin"
                assert r.headers["Cross-Origin-Embedder-Policy"] == "require-corp"


def test_build_writes_the_page(tmp_path, monkeypatch):
    """From an empty cache: the tracker is converted from the installed wheel. A real talking
    head (``web build`` runs it once on its own neutral before accepting it)."""
    from _onnx_models import synthetic_talking_head

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    _site_avatar(tmp_path)  # skips without what the page needs
    model = synthetic_talking_head(tmp_path)
    assert main(["web", "build", str(model), str(tmp_path / "site")]) == 0
    out = tmp_path / "site"
    for f in (*site.PAGE_FILES, *(f"ort/{f}" for f in site.ORT_FILES), "avatar.onnx", "schemes.json", "site.json",
              "models/face_detection.onnx", "models/face_landmark.onnx"):
        assert (out / f).is_file(), f
    paths = json.loads((out / "site.json").read_text())
    assert (paths["avatar"], paths["avatar_data"]) == ("avatar.onnx", "avatar.onnx.data")
    _assert_same_avatar((out / "avatar.onnx").read_bytes(), (out / "avatar.onnx.data").read_bytes(), model, tmp_path)


def _assert_same_avatar(graph: bytes, weights: bytes, model: Path, tmp_path: Path) -> None:
    """The page's avatar, its graph and its weights apart, is ``model``: the same metadata, the
    same weights, and ONNX Runtime gives the same output (a talking head: on its own neutral);
    the graph holds no large weight itself."""
    import onnx
    import onnxruntime as ort
    from onnx import numpy_helper

    folder = tmp_path / "split"
    folder.mkdir()
    (folder / "avatar.onnx").write_bytes(graph)
    (folder / "avatar.onnx.data").write_bytes(weights)
    a, b = onnx.load(str(folder / "avatar.onnx")), onnx.load(str(model))
    meta = {p.key: p.value for p in b.metadata_props}
    assert len(graph) < len(weights) and len(weights) >= max(len(numpy_helper.to_array(t).tobytes()) for t in b.graph.initializer)
    assert {p.key: p.value for p in a.metadata_props} == meta
    wa = {t.name: numpy_helper.to_array(t) for t in a.graph.initializer}
    wb = {t.name: numpy_helper.to_array(t) for t in b.graph.initializer}
    assert wa.keys() == wb.keys() and all(np.array_equal(wa[k], wb[k]) for k in wa)
    if "avatar_neutral" in meta:
        n = np.asarray(json.loads(meta["avatar_neutral"]), np.float32)
        x = {"driver": n[None], "driver_neutral": n}
    else:
        x = {"x": np.full((1, 1), 0.5, np.float32)}
    ya = ort.InferenceSession(str(folder / "avatar.onnx"), providers=["CPUExecutionProvider"]).run(None, x)[0]
    yb = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"]).run(None, x)[0]
    np.testing.assert_array_equal(ya, yb)


def test_serve_prints_the_url_and_serves_the_page(tmp_path):
    """``facesynth serve`` in a subprocess: one line with the 127.0.0.1 URL, the page and its
    headers there; SIGTERM stops it and removes the page's temporary folder."""
    import os
    import signal
    import subprocess
    import sys

    model = _site_avatar(tmp_path)
    (tmp_path / "tmp").mkdir()
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "TMPDIR": str(tmp_path / "tmp")}
    proc = subprocess.Popen([sys.executable, "-m", "facesynth", "serve", str(model), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line.startswith("open http://127.0.0.1:"), line + proc.stderr.read()
        url = line.split()[1]
        with urllib.request.urlopen(url) as r:
            assert b"facesynth live" in r.read()
            assert r.headers["Cross-Origin-Embedder-Policy"] == "require-corp"
        with urllib.request.urlopen(url + "avatar.onnx") as r, urllib.request.urlopen(url + "avatar.onnx.data") as d:
            _assert_same_avatar(r.read(), d.read(), model, tmp_path)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    assert list((tmp_path / "tmp").glob("facesynth-web-*")) == []


def readme_paths(args: list[str], folder, clip: str) -> list[str]:
    """README's step-4 arguments with the paths that README writes moved: an argument that is,
    or a ``key=`` value that is, a path under ``/tmp/`` goes into ``folder``, and the shared clip
    becomes ``clip``. Nothing else is rewritten: a checkout (and so ``clip``) under /tmp stays."""
    import re

    return [re.sub(r"(^|=)/tmp/", lambda m: f"{m.group(1)}{folder}/", a).replace("../shared/data/faces/lp_d6/video.mp4", clip)
            for a in args]


def test_readme_paths_leave_a_checkout_under_tmp_alone():
    """The README test from a checkout under /tmp: the clip's absolute path is /tmp/... too,
    and must reach the command unchanged."""
    clip = "/tmp/clone/../shared/data/faces/lp_d0/video.mp4"
    args = ["facesynth", "ingest", "../shared/data/faces/lp_d6/video.mp4", "--out", "/tmp/lp_d6", "data.path=/tmp/lp_d6",
            "hydra.run.dir=/tmp/lp_d6_run", "/tmp/lp_d6.onnx", "--note", "a/tmp/b"]
    assert readme_paths(args, "/tmp/pytest-7/t0", clip) == [
        "facesynth", "ingest", clip, "--out", "/tmp/pytest-7/t0/lp_d6", "data.path=/tmp/pytest-7/t0/lp_d6",
        "hydra.run.dir=/tmp/pytest-7/t0/lp_d6_run", "/tmp/pytest-7/t0/lp_d6.onnx", "--note", "a/tmp/b"]


def test_readme_live_page_path_runs_as_written(tmp_path, shared_clip_dir):
    """README's Getting started, step 5, command by command as written, on a shorter shared
    clip (lp_d0, 78 frames, in place of lp_d6) and in a temporary folder: MediaPipe ingest,
    training, the talking-head export, and ``facesynth serve`` serving that avatar."""
    import os
    import re
    import shlex
    import signal
    import subprocess
    import sys
    from pathlib import Path

    _site_avatar(tmp_path)  # skips without what the page needs
    root = Path(__file__).resolve().parents[1]
    step = (root / "README.md").read_text().split("**5. Drive an avatar from any video.**")[1].split("```bash\n")[1].split("```")[0]
    commands = [shlex.split(c) for c in re.split(r"\s*&&\s*", step.replace("\\\n", " ").strip())]
    assert [c[:2] for c in commands] == [["facesynth", "ingest"], ["facesynth", "train"], ["facesynth", "export"],
                                         ["facesynth", "serve"]]
    clip = str(shared_clip_dir("lp_d0") / "video.mp4")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "XDG_CACHE_HOME": str(tmp_path / "cache")}

    def local(args):
        return readme_paths(args, tmp_path, clip)

    for c in commands[:3]:
        proc = subprocess.run([sys.executable, "-m", "facesynth", *local(c)[1:]], env=env, capture_output=True,
                              text=True, timeout=600, cwd=tmp_path)
        assert proc.returncode == 0, (c, proc.stderr[-2000:])
    serve = local(commands[3])
    model = Path(serve[-1])
    assert model.is_file()
    proc = subprocess.Popen([sys.executable, "-m", "facesynth", *serve[1:], "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line.startswith("open http://127.0.0.1:"), line + proc.stderr.read()
        with urllib.request.urlopen(line.split()[1] + "avatar.onnx.data") as r:
            assert len(r.read()) > model.stat().st_size // 2  # the avatar's weights
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
