"""``facesynth app`` as a newcomer and a hostile user meet it: the driver's own frame rate,
the driver's video beside the rendering, progress while landmarks are detected, outputs
checked before any work and reopened after it (a full disk), outputs that are inputs, and
one-line errors for empty or face-less landmarks and meaningless --fps / --max-frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _disk import full_tmpfs
from _errors import one_error_line
from _faces import face_sequence_arrays, smooth_image
from _onnx_models import driving_landmarks, exported, synthetic_synthesizer

from facesynth.cli import main
from facesynth.errors import DiskFullError, FacesynthError

ROOT = Path(__file__).resolve().parents[1]
SIZE = 180  # the synthetic faces' frame side


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return exported("linear", tmp_path_factory.mktemp("onnx"))


@pytest.fixture(scope="module")
def avatar_path(tmp_path_factory) -> Path:
    """The synthetic model exported with its avatar metadata (neutral, shape space, own frame):
    the app drives it in relative motion, in the avatar's frame."""
    from facesynth.data import FaceSequence
    from facesynth.data.frames import ArrayFrames
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.onnx.synthesis import export_synthesizer

    frames, lm = face_sequence_arrays(n=24, seed=1)  # the frames synthetic_model() was fitted on
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    syn = synthetic_synthesizer("linear")
    return export_synthesizer(syn, tmp_path_factory.mktemp("avatar") / "avatar.onnx",
                              avatar_metadata(syn, lm, np.arange(len(lm)), seq))


def _driver_frames(n: int) -> np.ndarray:
    """uint8 (n, SIZE, SIZE, 3): smooth pictures that differ from frame to frame."""
    return np.stack([(smooth_image(SIZE, SIZE, 100 + i) * 255).astype(np.uint8) for i in range(n)])


def _write_video(path: Path, frames: np.ndarray, fps: float) -> Path:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, frames.shape[2:0:-1])
    for f in frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    return path


def _read_video(path: Path) -> tuple[list[np.ndarray], float]:
    cap = cv2.VideoCapture(str(path))
    fps, frames = cap.get(cv2.CAP_PROP_FPS), []
    while True:
        ok, f = cap.read()
        if not ok:
            return frames, fps
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))


def _ingest_folder(tmp_path: Path, n: int = 6, fps: float = 25.0) -> tuple[Path, Path, np.ndarray]:
    """An ingest folder as ``facesynth ingest`` writes it without --copy: landmarks.npy and a
    meta.json naming the driver video by its path elsewhere (no video.mp4 in the folder)."""
    video = _write_video(tmp_path / "driver_25fps.mp4", _driver_frames(n), fps)
    folder = tmp_path / "ingested"
    folder.mkdir()
    lm = driving_landmarks(seed=5, n=n)
    np.save(folder / "landmarks.npy", lm)
    (folder / "meta.json").write_text(json.dumps({"video": {"path": str(video), "fps": fps, "frames": n,
                                                            "width": SIZE, "height": SIZE}}))
    return folder, video, lm


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255**2 / max(np.mean((a.astype(float) - b.astype(float)) ** 2), 1e-9)))


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# ---------------------------------------------------------------- first contact
def test_app_writes_the_drivers_frame_rate(model_path, tmp_path, capsys, monkeypatch):
    folder, video, lm = _ingest_folder(tmp_path)
    base = ["app", "--model", str(model_path), "--no-progress"]
    np.save(tmp_path / "lm.npy", lm)
    cases = {  # output -> (arguments, the rate it must have)
        "folder.mp4": (["--landmarks", str(folder)], 25.0),  # meta.json's video.fps
        "explicit.mp4": (["--landmarks", str(folder), "--fps", "12.5"], 12.5),  # --fps wins
        "driver_video.mp4": (["--landmarks", str(tmp_path / "lm.npy"), "--driver-video", str(video)], 25.0),
        "bare.mp4": (["--landmarks", str(tmp_path / "lm.npy")], 30.0),  # nothing records a rate
        "video.mp4": (["--video", str(video)], 25.0),  # the video's own rate
    }
    # --video's landmarker (dlib, an extra) replaced by the driver's known landmarks
    import facesynth.runtime.app as app

    monkeypatch.setattr(app, "detect_video_landmarks", lambda frames, scheme, on_frame=None: lm[: len(list(frames()))])
    for name, (extra, fps) in cases.items():
        assert main([*base, *extra, "--out", str(tmp_path / name), "--json"]) == 0, capsys.readouterr().err
        frames, got = _read_video(tmp_path / name)
        assert got == pytest.approx(fps, abs=1e-3) and len(frames) == len(lm), name
        assert json.loads(capsys.readouterr().out.splitlines()[-1])["fps"] == pytest.approx(fps)


@pytest.mark.parametrize("which", ["model", "avatar"])
def test_side_by_side_shows_the_ingest_folders_video(model_path, avatar_path, tmp_path, which, capsys):
    # the left panel is the driver's own decoded frame, also for an avatar rendered in its own
    # frame (relative motion), where it used to be the avatar's still frame with the driver's dots
    folder, video, lm = _ingest_folder(tmp_path)
    out = tmp_path / "sbs.mp4"
    model = model_path if which == "model" else avatar_path
    assert main(["app", "--model", str(model), "--landmarks", str(folder), "--side-by-side", "--no-progress",
                 "--out", str(out)]) == 0, capsys.readouterr().err
    frames, _ = _read_video(out)
    driver, _ = _read_video(video)
    assert len(frames) == len(driver) == len(lm)
    for i, frame in enumerate(frames):
        left = frame[:, : frame.shape[1] // 2]
        assert left.shape == driver[i].shape
        assert _psnr(left, driver[i]) > 30  # its own frame (mp4v twice: lossy)
        assert _psnr(left, driver[i]) > max(_psnr(left, d) for j, d in enumerate(driver) if j != i) + 5


def test_video_landmark_detection_shows_progress_and_respects_quiet(model_path, tmp_path, capsys, monkeypatch):
    import facesynth.data.detect as detect
    import facesynth.runtime.app as app
    from facesynth.progress import set_quiet

    _, video, lm = _ingest_folder(tmp_path)
    calls = []

    def fake_detect(frames, detector=None, on_frame=None):  # dlib (an extra) replaced; the app's bar is real
        frames = list(frames)
        for i, _ in enumerate(frames):
            on_frame(i, "hog_up0")
        return detect.Detections(lm[: len(frames)], np.zeros((len(frames), 4), np.float32), ["hog_up0"] * len(frames),
                                 np.ones(len(frames), int))

    real_bar = app.bar

    def recording_bar(*a, **k):
        b = real_bar(*a, **k)
        calls.append((k.get("desc"), k.get("total"), b))
        return b

    monkeypatch.setattr(detect, "check_extra", lambda: None)
    monkeypatch.setattr(detect, "detect_landmarks", fake_detect)
    monkeypatch.setattr(app, "bar", recording_bar)
    args = ["app", "--model", str(model_path), "--video", str(video), "--out", str(tmp_path / "o.mp4")]
    try:
        assert main(args) == 0
        err = capsys.readouterr().err
        assert f"[facesynth] landmark detection: {len(lm)} of {len(lm)} frames of {video} with a face in" in err
        desc, total, b = calls[0]
        assert (desc, total, b.n) == ("landmarks", len(lm), len(lm))  # one step per detected frame
        assert main([*args, "--quiet"]) == 0
        assert "landmark detection" not in capsys.readouterr().err
        assert all(b.disable for desc, _, b in calls[2:])  # every bar of the quiet run is off
    finally:
        set_quiet(False)


# ------------------------------------------------- outputs checked before and after
def _dropping_writes(monkeypatch):
    """Every frame after a video's first is silently lost, as under OpenCV's FFmpeg writer
    on a full disk (it reports no error): the frames are counted, not written."""
    from facesynth.videofile import VideoOut

    real = VideoOut.write

    def write(self, rgb):
        if self.frames == 0:
            real(self, rgb)
        else:
            self.frames += 1

    monkeypatch.setattr(VideoOut, "write", write)


@pytest.mark.parametrize("disk_full", [False, True])
def test_a_video_that_does_not_reopen_whole_is_not_kept(model_path, tmp_path, capsys, monkeypatch, disk_full):
    import facesynth.videofile as videofile

    np.save(tmp_path / "lm.npy", driving_landmarks(seed=6, n=5))
    out = tmp_path / "out"
    out.mkdir()
    _dropping_writes(monkeypatch)
    if disk_full:
        monkeypatch.setattr(videofile, "free_bytes", lambda path: 0)
    assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--no-progress",
                 "--out", str(out / "o.mp4"), "--save-landmarks", str(out / "l.npy"), "--contact-sheet",
                 str(out / "s.png")]) == 2
    if disk_full:
        one_error_line(capsys.readouterr().err, "no space left on device", str(out / "o.mp4"))
    else:
        one_error_line(capsys.readouterr().err, str(out / "o.mp4"), "does not reopen as 5 frames", "found 1 frames")
    assert _listing(out) == []  # no video, no landmarks, no sheet, no temporary file


def test_every_video_writer_checks_what_it_wrote(tmp_path, monkeypatch):
    # transfer-expression's and transfer3d's videos go through the same check as the app's
    import facesynth.videofile as videofile
    from facesynth.eri.render import write_video
    from facesynth.mesh.preview import PreviewWriter

    frames = _driver_frames(3)
    assert write_video(tmp_path / "whole.mp4", iter(frames), 25.0) == 3
    assert len(_read_video(tmp_path / "whole.mp4")[0]) == 3
    _dropping_writes(monkeypatch)
    with pytest.raises(FacesynthError, match=r"eri.mp4: the video written does not reopen as 3 frames"):
        write_video(tmp_path / "eri.mp4", iter(frames), 25.0)
    monkeypatch.setattr(videofile, "free_bytes", lambda path: 0)
    preview = PreviewWriter(tmp_path / "mesh.mp4", 25.0)
    for f in frames:
        preview.write(f)
    with pytest.raises(DiskFullError, match=r"no space left on device writing .*mesh.mp4"):
        preview.close(ok=True)
    assert _listing(tmp_path) == ["whole.mp4"]


def test_check_video_against_opencv(tmp_path):
    from facesynth.videofile import check_video

    frames = _driver_frames(4)
    path = _write_video(tmp_path / "v.mp4", frames, 25.0)
    check_video(path, 4, (SIZE, SIZE), "v.mp4")  # whole: passes
    with pytest.raises(FacesynthError, match=r"v.mp4: .* as 5 frames of 180x180 \(found 4 frames of 180x180\)"):
        check_video(path, 5, (SIZE, SIZE), "v.mp4")
    with pytest.raises(FacesynthError, match=r"as 4 frames of 200x180"):
        check_video(path, 4, (200, SIZE), "v.mp4")
    data = path.read_bytes()
    cut = tmp_path / "cut.mp4"  # the index (moov, written last) lost
    cut.write_bytes(data[: data.index(b"moov") - 4])
    with pytest.raises(FacesynthError, match=r"found nothing readable"):
        check_video(cut, 4, (SIZE, SIZE), "cut.mp4")


FULL_DISK_APP = "import sys; from facesynth.cli import main; sys.exit(main(sys.argv[1:]))"


def test_full_disk_while_writing_the_video_real_tmpfs(avatar_path, tmp_path):
    lm = driving_landmarks(seed=7, n=60)
    np.save(tmp_path / "lm.npy", lm)
    app = [sys.executable, "-c", FULL_DISK_APP, "app", "--model", str(avatar_path), "--landmarks",
           str(tmp_path / "lm.npy"), "--fps", "25", "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    ok = subprocess.run([*app, "--out", str(tmp_path / "whole.mp4")], capture_output=True, text=True, cwd=ROOT, env=env)
    assert ok.returncode == 0, ok.stderr
    need = (tmp_path / "whole.mp4").stat().st_size
    with full_tmpfs(tmp_path / "M", size="3M", leave_kb=max(4, need // 2 // 1024)) as mnt:  # half the video's size
        p = subprocess.run([*app, "--out", str(mnt / "o.mp4")], capture_output=True, text=True, cwd=ROOT, env=env)
        assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
        one_error_line(p.stderr, "no space left on device", str(mnt / "o.mp4"))
        assert "frames ->" not in p.stdout  # nothing reported as written
        assert _listing(mnt) == ["filler"]


@pytest.mark.parametrize("flag", ["--contact-sheet", "--save-landmarks"])
def test_every_output_is_checked_before_rendering(model_path, tmp_path, capsys, flag):
    np.save(tmp_path / "lm.npy", driving_landmarks(seed=8, n=3))
    (tmp_path / "a_file").write_text("keep")
    bad = tmp_path / "a_file" / ("s.png" if flag == "--contact-sheet" else "l.npy")
    out = tmp_path / "O" / "o.mp4"
    assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--no-progress",
                 "--out", str(out), flag, str(bad)]) == 2
    one_error_line(capsys.readouterr().err, str(bad), "is a file, not a folder")
    assert not out.parent.exists() and (tmp_path / "a_file").read_text() == "keep"


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="a read-only bind mount needs root")
def test_read_only_folder_for_the_contact_sheet(model_path, tmp_path, capsys):
    np.save(tmp_path / "lm.npy", driving_landmarks(seed=8, n=3))
    ro = tmp_path / "RO"
    ro.mkdir()
    (ro / "old.png").write_bytes(b"old")
    mounted = subprocess.run(["mount", "--bind", str(ro), str(ro)], capture_output=True).returncode == 0
    try:
        if not mounted or subprocess.run(["mount", "-o", "remount,ro,bind", str(ro)], capture_output=True).returncode:
            pytest.skip("cannot make a read-only bind mount here")
        out = tmp_path / "O" / "o.mp4"
        assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--no-progress",
                     "--out", str(out), "--contact-sheet", str(ro / "s.png")]) == 2
        one_error_line(capsys.readouterr().err, str(ro / "s.png"), "not writable")
        assert not out.parent.exists() and _listing(ro) == ["old.png"]
    finally:
        if mounted:
            subprocess.run(["umount", str(ro)], capture_output=True)


def test_outputs_that_are_inputs_are_refused(model_path, tmp_path, capsys):
    folder, video, lm = _ingest_folder(tmp_path)
    np.save(tmp_path / "lm.npy", lm)
    bg = tmp_path / "bg.png"
    cv2.imwrite(str(bg), np.full((SIZE, SIZE, 3), 90, np.uint8))
    (tmp_path / "link.mp4").symlink_to(video)
    before = {p: p.read_bytes() for p in (tmp_path / "lm.npy", folder / "landmarks.npy", folder / "meta.json", bg, video)}
    listing = _listing(tmp_path)
    base = ["app", "--model", str(model_path), "--no-progress"]
    cases = [
        (["--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "lm.npy")], "lm.npy"),
        (["--landmarks", str(folder), "--out", str(tmp_path / "o.mp4"), "--save-landmarks",
          str(folder / "landmarks.npy")], "landmarks.npy"),
        (["--landmarks", str(folder), "--out", str(tmp_path / "link.mp4")], "link.mp4"),  # the ingest video, by a link
        (["--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "o.mp4"), "--background", str(bg),
          "--contact-sheet", str(bg)], "bg.png"),
        (["--landmarks", str(tmp_path / "lm.npy"), "--out", str(model_path)], model_path.name),
        (["--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "o.mp4"), "--save-landmarks",
          str(tmp_path / "x.npy"), "--contact-sheet", str(tmp_path / "o.mp4")], None),  # not an image name
    ]
    for extra, needle in cases:
        assert main([*base, *extra]) == 2
        one_error_line(capsys.readouterr().err, *([needle, "input"] if needle else ["--contact-sheet"]))
    assert {p: p.read_bytes() for p in before} == before and _listing(tmp_path) == listing


# ------------------------------------------------------------- one-line errors
@pytest.mark.parametrize("case", ["empty", "all_nan", "all_nan_first_rows"])
def test_landmarks_without_frames_or_faces(model_path, avatar_path, tmp_path, capsys, case):
    lm = driving_landmarks(seed=9, n=6)
    extra = []
    if case == "empty":
        lm = lm[:0]
    elif case == "all_nan":
        lm[:] = np.nan
    else:
        lm[:3] = np.nan
        extra = ["--max-frames", "3"]
    path = tmp_path / "lm.npy"
    np.save(path, lm)
    for model in (model_path, avatar_path):  # absolute and relative motion (a driver neutral is chosen)
        assert main(["app", "--model", str(model), "--landmarks", str(path), "--no-progress",
                     "--out", str(tmp_path / "o.mp4"), *extra]) == 2
        err = one_error_line(capsys.readouterr().err, str(path))
        assert ("holds no frames" in err) if case == "empty" else ("no frame has a face" in err)
        assert "--driver-neutral" not in err and "(0, 68, 2)" not in err
    assert _listing(tmp_path) == ["lm.npy"]


@pytest.mark.parametrize("option, value", [("--fps", "0"), ("--fps", "-5"), ("--fps", "nan"), ("--max-frames", "0"),
                                           ("--max-frames", "-2")])
def test_meaningless_fps_and_max_frames_are_refused(model_path, tmp_path, capsys, option, value):
    np.save(tmp_path / "lm.npy", driving_landmarks(seed=10, n=3))
    assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--no-progress",
                 "--out", str(tmp_path / "o" / "o.mp4"), option, value]) == 2
    one_error_line(capsys.readouterr().err, option, value)
    assert _listing(tmp_path) == ["lm.npy"]


def test_meta_json_frame_rate_is_checked(model_path, tmp_path, capsys):
    folder, _, _ = _ingest_folder(tmp_path)
    meta = json.loads((folder / "meta.json").read_text())
    meta["video"]["fps"] = "twenty-five"
    (folder / "meta.json").write_text(json.dumps(meta))
    assert main(["app", "--model", str(model_path), "--landmarks", str(folder), "--no-progress",
                 "--out", str(tmp_path / "o.mp4")]) == 2
    one_error_line(capsys.readouterr().err, str(folder / "meta.json"), "video.fps")
    assert not (tmp_path / "o.mp4").exists()

