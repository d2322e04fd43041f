"""A wheel built from the repository, installed in a fresh venv and run outside the checkout,
trains (``facesynth train``, its Hydra configs from the package), exports, renders
(``facesynth app``) and batches (``facesynth batch``, when the ingest extra is installed).

The new venv gets the wheel only (``--no-deps``); its dependencies are the current venv's,
reached through a path line in a ``.pth`` file (such a line does not run that folder's own
``.pth`` files, so the editable install of the checkout stays out of sight).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from importlib.util import find_spec
from pathlib import Path

import cv2
import numpy as np
import pytest

from facesynth.data.synthetic import make_synthetic_sequence

ROOT = Path(__file__).resolve().parents[1]
TINY = ["regressor=linear", "eval.frame_level=false", "eval.train_level=false", "eval.common_region=false",
        "eval.noise=[0]"]


def _wheel_venv(tmp: Path) -> Path:
    """Build the wheel from a copy of the sources (no build/ left in the checkout) and install
    it alone in a new venv under ``tmp``; the venv's ``bin`` folder."""
    src = tmp / "src"
    src.mkdir()
    shutil.copytree(ROOT / "facesynth", src / "facesynth", ignore=shutil.ignore_patterns("__pycache__", "node_modules"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    pip = [sys.executable, "-m", "pip"]
    subprocess.run([*pip, "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(tmp / "dist"), str(src)],
                   check=True, capture_output=True)
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], check=True,
                          capture_output=True, text=True).stdout.strip()
    Path(site, "_current_venv.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next((tmp / "dist").glob("facesynth-*.whl"))
    subprocess.run([*pip, "--python", str(py), "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True,
                   capture_output=True)
    return venv / "bin"


@pytest.mark.slow
def test_wheel_installed_outside_the_checkout_trains_exports_renders_and_batches(tmp_path):
    from importlib.metadata import PackageNotFoundError, version

    try:
        backend = int(version("setuptools").split(".")[0])
    except PackageNotFoundError:
        backend = 0
    if backend < 77:
        pytest.skip("building the wheel without isolation needs setuptools >= 77 (the 'test' extra installs it)")
    bin_dir = _wheel_venv(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}", OMP_NUM_THREADS="1")

    def run(*args: str) -> subprocess.CompletedProcess:
        proc = subprocess.run([str(a) for a in args], cwd=work, env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return proc

    where = run(bin_dir / "python", "-c", "import facesynth.runs.config as c; print(c.__file__); print(c.CONF_DIR)")
    module_file, conf_dir = where.stdout.split()
    assert Path(module_file).is_relative_to(bin_dir.parent) and Path(conf_dir).is_relative_to(bin_dir.parent)
    assert "experiment" in run("facesynth", "train", "--help").stdout  # Hydra's help, with the config groups

    run("facesynth", "train", *TINY, "data.n_frames=40", "data.size=128", f"hydra.run.dir={work / 'run'}", "quiet=true")
    metrics = json.loads((work / "run" / "metrics.json").read_text())
    assert metrics["psnr_ref"]["sadm"]["0"] > metrics["psnr_ref"]["mean_texture"]["0"]
    assert (work / "run" / "train.log").is_file()

    run("facesynth", "export", work / "run", "--out", work / "m.onnx", "--components", "8", "--quiet")
    lm = make_synthetic_sequence(n_frames=40, size=128, seed=0).landmarks[-5:]
    np.save(work / "lm.npy", lm)
    run("facesynth", "app", "--model", work / "m.onnx", "--landmarks", work / "lm.npy", "--out", work / "o.mp4", "--quiet")
    cap = cv2.VideoCapture(str(work / "o.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5 and cap.read()[0]
    cap.release()

    # the live page ships in the wheel: without its npm packages, build says how to get them
    run("facesynth", "export", work / "run", "--out", work / "head.onnx", "--talking-head", "--quiet")
    env["XDG_CACHE_HOME"] = str(work / "cache")
    built = subprocess.run(["facesynth", "web", "build", work / "head.onnx", work / "site"], cwd=work, env=env,
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 2 and "facesynth web setup" in built.stderr and not (work / "site").exists(), built.stderr
    if shutil.which("npm") and find_spec("tflite") and find_spec("mediapipe"):
        run("facesynth", "web", "setup")  # npm ci of the wheel's lockfile, beside the installed page
        run("facesynth", "web", "build", work / "head.onnx", work / "site")
        for f in ("index.html", "worker.js", "tracker.js", "ort/ort-wasm-simd-threaded.wasm", "models/face_landmark.onnx", "avatar.onnx",
                  "avatar.onnx.data"):
            assert (work / "site" / f).is_file(), f

    if find_spec("dlib") is None or find_spec("face_recognition_models") is None:
        return  # batch ingests with dlib (the ingest extra)
    frames = make_synthetic_sequence(n_frames=24, size=192, seed=3).load_frames()
    (work / "vids").mkdir()
    vw = cv2.VideoWriter(str(work / "vids" / "synth.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (192, 192))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    out = run("facesynth", "batch", work / "vids", "--out", work / "b", "--sequential", "--min-frames", "10",
              "--components", "8", "--json", "--no-progress", *TINY)
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert (figures["ok"], figures["failed"]) == (1, 0)
    assert (work / "b" / "synth" / "model.onnx").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("entry", [["-m", "facesynth", "train"], [str(ROOT / "train.py")]])
def test_train_entry_points_are_one_app(entry, tmp_path):
    """``facesynth train`` and ``python train.py``: the same help, and a bad option is exit 2."""
    out = subprocess.run([sys.executable, *entry, "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("facesynth train [OVERRIDE ...]")
    assert "experiment: " in out.stdout and "regressor: krr, linear, mlp, poly2, svr" in out.stdout
    bad = subprocess.run([sys.executable, *entry, "regressor=nope"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "Could not find 'regressor/nope'" in bad.stderr
    assert not (tmp_path / "runs").exists()
