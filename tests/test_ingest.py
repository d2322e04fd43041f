"""Video ingest (dlib HOG detector + 68-point predictor): reproduction of the shipped
landmarks, the written folder layout, options, and the error paths."""

import json
import sys
from importlib.util import find_spec

import cv2
import numpy as np
import pytest

from facesynth.cli import main
from facesynth.data import load_sequence, read_pts
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError, MissingExtraError

needs_dlib = pytest.mark.skipif(
    find_spec("dlib") is None or find_spec("face_recognition_models") is None, reason="ingest extra not installed"
)


def _write_video(path, frames_rgb, fps=30.0):
    h, w = frames_rgb[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for f in frames_rgb:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


@pytest.fixture(scope="module")
def synth_video(tmp_path_factory):
    seq = make_synthetic_sequence(n_frames=10, size=256, seed=5)
    path = _write_video(tmp_path_factory.mktemp("vid") / "synth.avi", seq.load_frames())
    return path, seq


@pytest.fixture(scope="module")
def detector():
    from facesynth.data.detect import LandmarkDetector

    return LandmarkDetector()


@pytest.mark.shared
@needs_dlib
def test_cli_reproduces_shipped_landmarks(shared_clip_dir, tmp_path, capsys):
    clip = shared_clip_dir("lp_d6")
    out = tmp_path / "lp_d6"
    rc = main(["ingest", str(clip / "video.mp4"), "--out", str(out), "--max-frames", "40",
               "--export-pts", "--copy", "--no-progress", "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames_processed"] == 40 and summary["frames_per_s"] > 0
    lm = np.load(out / "landmarks.npy")
    ref = np.load(clip / "landmarks.npy")[:40]
    assert lm.dtype == np.float32 and lm.shape == (40, 68, 2)
    assert np.median(np.linalg.norm(lm - ref, axis=-1)) <= 1.5
    meta = json.loads((out / "meta.json").read_text())
    shipped = json.loads((clip / "meta.json").read_text())
    for key in ("width", "height", "fps"):
        assert meta["video"][key] == shipped["video"][key]
    assert meta["video"]["frames"] == shipped["video"]["frames"]
    assert meta["video"]["file"] == "video.mp4" and (out / "video.mp4").stat().st_size == (clip / "video.mp4").stat().st_size
    assert meta["landmarks"]["shape"] == [40, 68, 2] and meta["stats"]["detection_rate"] == 1.0
    assert meta["landmarks"]["scheme"] == "ibug68" and summary["scheme"] == "ibug68"
    assert "dlib" in meta["detector_versions"]
    # .pts: one per frame, 1-based on disk, read back 0-based
    assert len(list((out / "pts").glob("*.pts"))) == 40
    np.testing.assert_allclose(read_pts(out / "pts" / "000007.pts"), lm[7], atol=1e-3)
    assert (out / "pts" / "000007.pts").read_text().splitlines()[3] == f"{lm[7, 0, 0] + 1:.3f} {lm[7, 0, 1] + 1:.3f}"
    # readable by the data layer; frames decode from the copied video
    seq = load_sequence(out)
    assert len(seq) == 40 and seq.meta["source_sha256"] == meta["video"]["sha256"] and seq.scheme == "ibug68"
    cap = cv2.VideoCapture(str(clip / "video.mp4"))
    ok, bgr = cap.read()
    np.testing.assert_array_equal(seq.frame(0), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


@pytest.mark.shared
@needs_dlib
def test_downscaled_detection_matches_shipped_landmarks(shared_clip_dir, detector, tmp_path):
    # lp_s18 is 1280x720 (W x H): detection runs on a 640-px copy, the box is scaled back and the
    # predictor runs at full resolution, as for the shipped landmarks.
    from facesynth.data.ingest import ingest_video

    clip = shared_clip_dir("lp_s18")
    seq = ingest_video(clip / "video.mp4", tmp_path / "s18", max_frames=6, detector=detector)
    ref = np.load(clip / "landmarks.npy")[:6]
    assert seq.image_size == (720, 1280)
    assert np.median(np.linalg.norm(seq.landmarks - ref, axis=-1)) <= 1.5


@needs_dlib
def test_dlib_finds_the_synthetic_face_near_its_landmarks(synth_video, detector):
    # An independent check of the synthetic subject's plausibility: a real face
    # detector/landmarker trained on photographs agrees with its landmarks.
    from facesynth.data.detect import detect_landmarks

    _, seq = synth_video
    det = detect_landmarks(seq.iter_frames(), detector)
    assert det.counts()["hog_up0"] == len(seq) and det.detection_rate == 1.0
    err = np.linalg.norm(det.landmarks - seq.landmarks, axis=-1)
    iod = np.linalg.norm(seq.landmarks[:, 45] - seq.landmarks[:, 36], axis=1).mean()
    assert np.median(err) < 0.05 * iod
    assert np.median(err[:, 36:48]) < 0.03 * iod  # eyes


@needs_dlib
def test_every_and_max_frames_keep_frame_numbers(synth_video, detector, tmp_path):
    from facesynth.data.ingest import ingest_video

    path, truth = synth_video
    seq = ingest_video(path, tmp_path / "o", every=3, max_frames=8, detector=detector)
    lm = np.load(tmp_path / "o" / "landmarks.npy")
    assert lm.shape == (8, 68, 2)
    has = np.isfinite(lm).all(axis=(1, 2))
    assert list(np.flatnonzero(has)) == [0, 3, 6] and np.isnan(lm[~has]).all()
    assert list(seq.frame_index) == [0, 3, 6] and seq.meta["dropped_frames"] == 5
    meta = json.loads((tmp_path / "o" / "meta.json").read_text())
    assert meta["video"]["path"] == str(path.resolve()) and meta["video"]["frames"] == 10
    assert meta["stats"]["frames_processed"] == 3 and meta["stats"]["detection_rate"] == 1.0
    assert np.median(np.linalg.norm(seq.landmarks - truth.landmarks[[0, 3, 6]], axis=-1)) < 4.0


@needs_dlib
def test_missed_frame_reuses_previous_box_within_limit(synth_video, detector, monkeypatch):
    from facesynth.data.detect import detect_landmarks

    _, seq = synth_video
    face, blank = seq.frame(0), np.full_like(seq.frame(0), 128)
    det = detect_landmarks([face, blank, blank, face, None], detector)
    assert det.sources == ["hog_up0", "previous_box", "previous_box", "hog_up0", "skipped"]
    np.testing.assert_array_equal(det.boxes[1], det.boxes[0])
    assert np.isfinite(det.landmarks[:4]).all() and np.isnan(det.landmarks[4]).all()
    monkeypatch.setattr(detector, "reuse_limit", 1)
    detector.reset()
    det = detect_landmarks([face, blank, blank], detector)
    assert det.sources == ["hog_up0", "previous_box", "miss"] and np.isnan(det.landmarks[2]).all()
    assert det.detection_rate == pytest.approx(2 / 3)


@needs_dlib
def test_unreadable_and_faceless_videos_are_one_line_errors(tmp_path, capsys):
    bad = tmp_path / "bad.mp4"
    bad.write_text("not a video")
    out = tmp_path / "out"
    assert main(["ingest", str(bad), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "bad.mp4: unreadable video" in err and "\n" not in err
    assert main(["ingest", str(tmp_path / "nope.mp4"), "--out", str(out)]) == 2
    assert "video file not found" in capsys.readouterr().err
    gray = _write_video(tmp_path / "gray.avi", [np.full((120, 160, 3), 90, np.uint8)] * 5)
    assert main(["ingest", str(gray), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "gray.avi: no face found in any of the 5 frames processed" in err and "\n" not in err
    assert not out.exists()  # nothing half-written


def test_missing_extra_names_the_pip_command(monkeypatch, tmp_path, capsys):
    import facesynth.data.detect as detect

    monkeypatch.setitem(sys.modules, "dlib", None)  # makes `import dlib` raise ImportError
    with pytest.raises(MissingExtraError, match=r"dlib is not installed.*pip install 'facesynth\[ingest\]'"):
        detect.LandmarkDetector()
    assert main(["ingest", str(tmp_path / "v.mp4"), "--out", str(tmp_path / "o")]) == 2
    assert "pip install 'facesynth[ingest]'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    monkeypatch.setattr(detect, "find_spec", lambda name: None)
    with pytest.raises(MissingExtraError, match="face_recognition_models is not installed"):
        detect.predictor_path()


@needs_dlib
def test_bad_options_are_errors(synth_video, detector, tmp_path):
    from facesynth.data.ingest import ingest_video

    path, _ = synth_video
    with pytest.raises(FacesynthError, match="every must be >= 1"):
        ingest_video(path, tmp_path / "o", every=0, detector=detector)
    (tmp_path / "file").write_text("")
    with pytest.raises(FacesynthError, match="not a folder"):
        ingest_video(path, tmp_path / "file", detector=detector)
