"""``facesynth batch``: many videos -> one trained, evaluated, exported subject each, on Ray
(local runtime, 2 CPUs) or one after another; failures reported, re-runs resumable."""

import csv
import json
import shutil
import tempfile
from importlib.util import find_spec
from pathlib import Path

import cv2
import numpy as np
import pytest

from facesynth.batch.discover import find_videos, subject_names
from facesynth.cli import main
from facesynth.data import load_sequence
from facesynth.data.synthetic import make_synthetic_sequence

needs_dlib = pytest.mark.skipif(
    find_spec("dlib") is None or find_spec("face_recognition_models") is None, reason="ingest extra not installed"
)
CHEAP = ["regressor=linear", "eval.frame_level=false"]


def _write_video(path: Path, frames_rgb, fps: float = 25.0) -> Path:
    h, w = frames_rgb[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for f in frames_rgb:
        vw.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
    vw.release()
    return path


def _no_face_video(path: Path, n: int = 20) -> Path:
    """A plain moving gradient: no face for the detector to find."""
    g = np.tile(np.linspace(0, 255, 96).astype(np.uint8), (96, 1))
    return _write_video(path, [np.dstack([g, np.roll(g, i, 1), g.T]) for i in range(n)])


def _summary(out: Path) -> dict[str, dict]:
    with open(out / "summary.csv", newline="") as f:
        return {r["subject"]: r for r in csv.DictReader(f)}


def _mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()
            and p.name not in ("subject.log", "result.json")}


def _check_subject(folder: Path, row: dict, shipped_landmarks: np.ndarray) -> None:
    """The subject's artifacts are valid: its landmarks reproduce the shipped ones, the
    summary carries the run's own metrics, and the ONNX model renders in ONNX Runtime."""
    from facesynth.runtime import Renderer

    lm = np.load(folder / "data" / "landmarks.npy")
    assert lm.shape == (60, 68, 2) and lm.dtype == np.float32
    assert np.median(np.linalg.norm(lm - shipped_landmarks[:60], axis=-1)) <= 1.5
    seq = load_sequence(folder / "data")
    metrics = json.loads((folder / "run" / "metrics.json").read_text())
    assert metrics["data"]["fingerprint"] == seq.fingerprint
    assert (int(row["frames"]), int(row["train_frames"]), int(row["test_frames"])) == (60, 45, 15)
    for col, key in (("psnr_sadm", "sadm"), ("psnr_mean_texture", "mean_texture"), ("psnr_oracle", "oracle")):
        assert float(row[col]) == pytest.approx(metrics["psnr_ref"][key]["0"], rel=1e-9)
    assert float(row["psnr_oracle"]) > float(row["psnr_mean_texture"])  # the oracle bounds the baseline
    r = Renderer(folder / "model.onnx")
    assert r.metadata["data_fingerprint"] == seq.fingerprint and r.metadata["regressor"] == "linear"
    crop, mask, _ = r.render(seq.landmarks[-3:])
    assert np.isfinite(crop).all() and mask.sum() > 100
    assert int(row["export_bytes"]) == (folder / "model.onnx").stat().st_size
    assert "ran ingest+train+export" in (folder / "subject.log").read_text()


@pytest.fixture(scope="module")
def ray_local():
    """A local Ray runtime on 2 CPUs for the module (Ray's files in a short temp folder,
    removed afterwards; its processes end with ray.shutdown)."""
    ray = pytest.importorskip("ray")
    tmp = tempfile.mkdtemp(prefix="fsray", dir="/tmp")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, _temp_dir=tmp)
    try:
        yield ray
    finally:
        ray.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.mark.shared
@pytest.mark.slow
@needs_dlib
def test_batch_on_ray_reports_failures_and_resumes(shared_clip_dir, ray_local, tmp_path, capsys):
    clips = {"lp_d6": shared_clip_dir("lp_d6"), "lp_d10": shared_clip_dir("lp_d10")}
    videos = tmp_path / "videos"
    videos.mkdir()
    for name, clip in clips.items():
        (videos / f"{name}.mp4").symlink_to(clip / "video.mp4")
    _no_face_video(videos / "blank.avi")
    out = tmp_path / "out"
    args = ["batch", str(videos), "--out", str(out), "--max-frames", "60", "--no-progress", *CHEAP]

    # First run: two subjects complete, the clip without a face fails with its reason.
    assert main(args) == 1
    rows = _summary(out)
    assert sorted(rows) == ["blank", "lp_d10", "lp_d6"]
    assert rows["blank"]["status"] == "failed" and "no face found" in rows["blank"]["reason"]
    assert "blank" in capsys.readouterr().err
    for name, clip in clips.items():
        assert rows[name]["status"] == "ok" and rows[name]["ran"] == "ingest+train+export" and not rows[name]["reason"]
        _check_subject(out / name, rows[name], np.load(clip / "landmarks.npy"))
    assert "| lp_d6 | ok |" in (out / "summary.md").read_text()
    assert cv2.imread(str(out / "summary.png")) is not None
    # Ray never ran more subjects at once than the 2 CPUs hold (1 CPU each)
    spans = [json.loads((out / n / "result.json").read_text()) for n in rows]
    assert max(sum(s["started"] <= t["started"] < s["finished"] for s in spans) for t in spans) <= 2
    first = {name: _mtimes(out / name) for name in clips}

    # Second run: the complete subjects are skipped (nothing rewritten), the failed one retried.
    assert main(args) == 1
    rows2 = _summary(out)
    assert {n: rows2[n]["status"] for n in rows2} == {"lp_d6": "skipped", "lp_d10": "skipped", "blank": "failed"}
    assert all(_mtimes(out / name) == first[name] for name in clips)
    assert rows2["lp_d6"]["psnr_sadm"] == rows["lp_d6"]["psnr_sadm"]

    # A lost artifact (the trained regressor's weights): only that subject is redone, from training on.
    (out / "lp_d10" / "run" / "sadm" / "regressor.safetensors").unlink()
    assert main(args) == 1
    rows3 = _summary(out)
    assert rows3["lp_d10"]["status"] == "ok" and rows3["lp_d10"]["ran"] == "train+export"
    assert rows3["lp_d6"]["status"] == "skipped" and _mtimes(out / "lp_d6") == first["lp_d6"]
    assert _mtimes(out / "lp_d10")["data/landmarks.npy"] == first["lp_d10"]["data/landmarks.npy"]
    # same data, same seed: the retrained subject has the same figures
    assert float(rows3["lp_d10"]["psnr_sadm"]) == pytest.approx(float(rows["lp_d10"]["psnr_sadm"]), abs=1e-6)
    _check_subject(out / "lp_d10", rows3["lp_d10"], np.load(clips["lp_d10"] / "landmarks.npy"))


@pytest.mark.slow
@needs_dlib
def test_sequential_fallback_without_ray(tmp_path, monkeypatch, capsys):
    from facesynth.batch import executor

    monkeypatch.setattr(executor, "ray_available", lambda: False)
    seq = make_synthetic_sequence(n_frames=40, size=256, seed=3)
    frames = seq.load_frames()
    videos = tmp_path / "in"
    videos.mkdir()
    _write_video(videos / "synth.avi", frames)
    _write_video(videos / "short.avi", frames[:12])
    _no_face_video(videos / "blank.avi")
    out = tmp_path / "out"
    rc = main(["batch", str(videos), "--out", str(out), "--no-progress", "--json", *CHEAP])
    captured = capsys.readouterr()
    assert rc == 1
    assert "Ray is not installed" in captured.err and "one after another" in captured.err
    figures = json.loads(captured.out.strip().splitlines()[-1])
    assert (figures["ok"], figures["failed"], figures["executor"]) == (1, 2, "sequential")
    rows = _summary(out)
    assert rows["synth"]["status"] == "ok" and int(rows["synth"]["face_frames"]) == 40
    assert rows["short"]["status"] == "failed"
    assert rows["short"]["reason"] == "too short: 12 frames with a face, fewer than the 30 needed (--min-frames)"
    assert rows["blank"]["status"] == "failed" and "no face found" in rows["blank"]["reason"]
    assert (out / "synth" / "model.onnx").is_file() and not (out / "short" / "run").exists()


def test_subject_names_are_unique_and_readable(tmp_path):
    for rel in ("a/lp_d6/video.mp4", "a/lp_d10/video.mp4", "b/x.MOV", "b/notes.txt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    found = find_videos(tmp_path)
    assert [p.name for p in found] == ["video.mp4", "video.mp4", "x.MOV"]
    assert subject_names(found) == ["lp_d10", "lp_d6", "x"]
    assert subject_names(find_videos(str(tmp_path / "a" / "*" / "video.mp4"))) == ["lp_d10", "lp_d6"]
    same = [tmp_path / "p" / "s.mp4", tmp_path / "q" / "p" / "s.mp4"]
    assert subject_names(same) == ["p_s", "q_p_s"]


def test_bad_input_is_one_line_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert "no such folder or file" in capsys.readouterr().err
    (tmp_path / "v.mp4").write_bytes(b"")
    assert main(["batch", str(tmp_path / "v.mp4"), "--out", str(out), "regresor=linear"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: training config overrides") and "regresor" in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_hydra_sweep_runs_jobs_in_parallel_with_the_joblib_launcher(tmp_path):
    # `train.py -m hydra/launcher=joblib`: the two jobs run in two worker processes at the same
    # time, and the sweep table is written as with the default launcher.
    import subprocess
    import sys

    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    root = Path(__file__).resolve().parents[1]
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "train.py", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
           "hydra.job_logging.formatters.simple.format='pid=%(process)d %(message)s'", f"hydra.sweep.dir={sweep}",
           "data.n_frames=40", "eval.frame_level=false", "regressor=linear,poly2"]
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-2000:]
    jobs = [sweep / "0_linear", sweep / "1_poly2"]
    pids = [{line.split()[0] for line in (j / "train.log").read_text().splitlines() if line.startswith("pid=")} for j in jobs]
    assert all(len(p) == 1 for p in pids) and pids[0] != pids[1]
    assert f"pid={proc.pid}" not in pids[0] | pids[1]
    # each job's span, from its first file (.hydra/config.yaml) to its last (metrics.json): they overlap
    spans = [((j / ".hydra" / "config.yaml").stat().st_mtime_ns, (j / "metrics.json").stat().st_mtime_ns) for j in jobs]
    assert spans[0][0] < spans[1][1] and spans[1][0] < spans[0][1]
    rows = json.loads((sweep / "comparison.json").read_text())
    assert [r["regressor"] for r in rows] == ["linear", "poly2"]


def test_unreachable_cluster_fails_fast_with_one_line(tmp_path, capsys):
    pytest.importorskip("ray")
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    _no_face_video(tmp_path / "blank.avi")
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "blank.avi"), "--out", str(out), "--address", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"error: Ray cluster at 127.0.0.1:{port}: nothing answers there (Connection refused)"
    assert not out.exists()
