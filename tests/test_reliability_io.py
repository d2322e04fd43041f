"""Issue 15, outputs on disk (rows 8, 11, 12, 15): temp files are ours and are removed on
SIGTERM and on exceptions, a SIGKILL leftover is removed by the next write, ingest checks
its output folder before any work and replaces it as a whole, a folder mixing two ingests
is refused."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from facesynth.cli import main
from facesynth.data import load_sequence
from facesynth.errors import FacesynthError
from facesynth.io import TMP_TAG, atomic_dir, atomic_path, save_npy, write_bytes

ROOT = Path(__file__).resolve().parents[1]
WRITER = """
import sys
from facesynth.io import atomic_path, install_sigterm_handler
install_sigterm_handler()
with atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"x" * 100000)
    print(tmp.name, flush=True)
    sys.stdin.read()  # blocks until the parent signals us
"""


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def _writer(target: Path) -> tuple[subprocess.Popen, str]:
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    name = p.stdout.readline().strip()
    return p, name


def test_row11_sigterm_removes_the_temp_file(tmp_path):
    target = tmp_path / "out.mp4"
    p, name = _writer(target)
    assert name.startswith(".out.mp4" + TMP_TAG) and name.endswith(".mp4")
    assert _listing(tmp_path) == [name]
    p.send_signal(signal.SIGTERM)
    p.communicate(timeout=60)
    assert p.returncode == 128 + signal.SIGTERM
    assert _listing(tmp_path) == []


def test_row11_sigkill_leftover_is_removed_by_the_next_write(tmp_path):
    target = tmp_path / "model.onnx"
    p, name = _writer(target)
    p.kill()
    p.communicate(timeout=60)
    assert _listing(tmp_path) == [name]  # a SIGKILL cannot be caught: the temp stays, recognisably ours
    write_bytes(target, b"new")
    assert _listing(tmp_path) == ["model.onnx"]
    assert target.read_bytes() == b"new"


def test_row11_a_live_writers_temp_is_not_touched(tmp_path):
    target = tmp_path / "a.bin"
    p, name = _writer(target)
    try:
        write_bytes(target, b"other")
        assert _listing(tmp_path) == sorted([name, "a.bin"])
    finally:
        p.kill()
        p.communicate(timeout=60)


def test_row11_exception_removes_temp_file_and_folder(tmp_path):
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "f.npy") as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("boom")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "d") as tmp:
        (tmp / "new.txt").write_text("new")
        raise RuntimeError("boom")
    assert _listing(tmp_path) == ["d"] and _listing(tmp_path / "d") == ["old.txt"]


@pytest.mark.parametrize("name", ["x.raw", "x", "x.npy"])
def test_row1_save_npy_writes_exactly_the_name(tmp_path, name):
    save_npy(tmp_path / name, np.arange(3))
    assert _listing(tmp_path) == [name]
    np.testing.assert_array_equal(np.load(tmp_path / name), np.arange(3))


def test_row15_written_files_have_the_usual_permissions(tmp_path):
    from safetensors.numpy import save_file

    with atomic_path(tmp_path / "t.safetensors") as tmp:
        save_file({"a": np.zeros(3, np.float32)}, str(tmp))
    write_bytes(tmp_path / "t.json", b"{}")
    modes = {p.name: stat.S_IMODE(os.stat(p).st_mode) for p in tmp_path.iterdir()}
    assert modes["t.safetensors"] == modes["t.json"]


# ------------------------------------------------------------------ ingest
class _FakeDetector:
    """Stands in for dlib: the synthetic video's own landmarks, no detection."""

    def __init__(self, lm):
        self.lm = lm

    def reset(self):
        pass

    def describe(self):
        return {"name": "fake"}


@pytest.fixture
def fake_ingest(monkeypatch, tmp_path):
    """A 6-frame synthetic video and an ingest that "detects" its true landmarks."""
    from facesynth.data import ingest
    from facesynth.data.detect import Detections
    from facesynth.data.synthetic import make_synthetic_sequence

    seq = make_synthetic_sequence(n_frames=6, size=128, seed=3)
    path = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (128, 128))
    for f in seq.load_frames():
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    calls = {"n": 0}

    def detect(frames, det, on_frame=None):
        n = sum(1 for _ in frames)
        calls["n"] += 1
        lm = det.lm[:n]
        return Detections(lm, np.zeros((n, 4), np.float32), ["hog_up0"] * n, np.ones(n, int), {"detect": 0.0, "landmarks": 0.0})

    monkeypatch.setattr(ingest, "detect_landmarks", detect)
    monkeypatch.setattr(ingest, "detector_versions", lambda: {"fake": "0"})
    return path, _FakeDetector(seq.landmarks), calls


def test_row8_ingest_out_under_a_file_fails_before_any_work(fake_ingest, tmp_path, capsys):
    path, det, calls = fake_ingest
    (tmp_path / "afile").write_text("x")
    from facesynth.data.ingest import ingest_video

    with pytest.raises(FacesynthError, match="afile"):
        ingest_video(path, tmp_path / "afile" / "out", detector=det)
    assert calls["n"] == 0
    assert main(["ingest", str(path), "--out", str(tmp_path / "afile" / "out")]) == 2
    err = capsys.readouterr().err
    assert "afile" in err and err.count("\n") == 1
    assert _listing(tmp_path) == ["afile", "v.avi"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_row8_ingest_out_in_a_read_only_folder_fails_before_any_work(fake_ingest, tmp_path):
    path, det, calls = fake_ingest
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    from facesynth.data.ingest import ingest_video

    try:
        with pytest.raises(FacesynthError, match="not writable|permission"):
            ingest_video(path, ro / "out", detector=det)
    finally:
        ro.chmod(0o755)
    assert calls["n"] == 0


def test_row8_ingest_refuses_a_foreign_nonempty_folder(fake_ingest, tmp_path):
    path, det, _ = fake_ingest
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    from facesynth.data.ingest import ingest_video

    with pytest.raises(FacesynthError, match="not an ingest folder"):
        ingest_video(path, tmp_path / "mine", detector=det)
    assert _listing(tmp_path / "mine") == ["thesis.tex"]


def test_row12_crash_before_meta_leaves_the_old_folder_whole(fake_ingest, tmp_path, monkeypatch):
    from facesynth.data import ingest

    path, det, _ = fake_ingest
    out = tmp_path / "clip"
    ingest.ingest_video(path, out, max_frames=4, detector=det)
    old = {p.name: p.read_bytes() for p in out.iterdir()}

    def crash(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ingest, "write_json", crash)
    with pytest.raises(OSError):
        ingest.ingest_video(path, out, max_frames=6, detector=det)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == old  # the old folder, whole
    assert _listing(tmp_path) == ["clip", "v.avi"]  # no hidden temp folder
    assert len(load_sequence(out)) == 4


def test_row12_landmarks_from_another_ingest_are_refused(fake_ingest, tmp_path):
    from facesynth.data.ingest import ingest_video

    path, det, _ = fake_ingest
    ingest_video(path, tmp_path / "a", max_frames=4, detector=det)
    ingest_video(path, tmp_path / "b", max_frames=6, detector=det)
    (tmp_path / "a" / "landmarks.npy").write_bytes((tmp_path / "b" / "landmarks.npy").read_bytes())
    with pytest.raises(FacesynthError, match="landmarks.npy.*meta.json"):
        load_sequence(tmp_path / "a")
    lm = np.load(tmp_path / "b" / "landmarks.npy")
    lm[0, 0, 0] += 1.0  # same shape, other content
    np.save(tmp_path / "b" / "landmarks.npy", lm)
    with pytest.raises(FacesynthError, match="SHA-256"):
        load_sequence(tmp_path / "b")


def test_row13_fewer_landmark_rows_than_frames_warns(fake_ingest, tmp_path, caplog):
    """An ingest limited by max_frames is not "a shorter clip": no warning; the same rows
    without that record (landmarks of a shorter clip) are warned about."""
    from facesynth.data.ingest import ingest_video

    path, det, _ = fake_ingest
    ingest_video(path, tmp_path / "a", max_frames=4, detector=det)
    caplog.clear()
    with caplog.at_level("WARNING"):
        seq = load_sequence(tmp_path / "a")
    assert len(seq) == 4
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == []
    meta = json.loads((tmp_path / "a" / "meta.json").read_text())
    assert len(meta["landmarks"]["sha256"]) == 64 and meta["landmarks"]["max_frames"] == 4
    meta["landmarks"]["max_frames"] = None
    (tmp_path / "a" / "meta.json").write_text(json.dumps(meta))
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert len(load_sequence(tmp_path / "a")) == 4
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "4 landmark rows for 6 video frames" in warnings[0]


def test_row8_read_only_folder_is_refused_before_any_work(fake_ingest, tmp_path, monkeypatch):
    """As root (where permissions do not bite) the check is shown with os.access denied."""
    import facesynth.io as fio
    from facesynth.data.ingest import ingest_video

    path, det, calls = fake_ingest
    monkeypatch.setattr(fio.os, "access", lambda p, mode: Path(p) != tmp_path)
    with pytest.raises(FacesynthError, match=f"{tmp_path} is not writable"):
        ingest_video(path, tmp_path / "out", detector=det)
    assert calls["n"] == 0 and _listing(tmp_path) == ["v.avi"]


def test_folders_of_dead_processes_are_removed_and_live_ones_kept(tmp_path):
    """``io.remove_dead_pid_folders``, which ``serve`` (its page builds) and the studio (its job
    folders in the library) clean up with: a dead PID's folder goes; this process's, another
    name's and a link stay."""
    import subprocess

    from facesynth.io import remove_dead_pid_folders
    from facesynth.web.site import STALE_PREFIX
    from facesynth.web.studio import WORK_PREFIX

    dead = subprocess.Popen(["true"])
    dead.wait()
    for prefix in (STALE_PREFIX, WORK_PREFIX):
        root = tmp_path / prefix.strip(".-")
        gone, alive, other = root / f"{prefix}{dead.pid}-a", root / f"{prefix}{os.getpid()}-b", root / "keep-1-c"
        for d in (gone, alive, other):
            (d / "x").mkdir(parents=True)
        (root / f"{prefix}{dead.pid}-link").symlink_to(other)
        assert remove_dead_pid_folders(root, prefix) == [gone]
        assert sorted(p.name for p in root.iterdir()) == sorted([alive.name, other.name, f"{prefix}{dead.pid}-link"])
