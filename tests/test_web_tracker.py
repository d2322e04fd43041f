"""The page's face tracker: MediaPipe's .tflite models converted to ONNX (facesynth.web.convert)
and its crop-and-track steps (facesynth.web.track, mirrored by web/page/tracker.js), against Python
MediaPipe on the same frames of a shared clip."""

import numpy as np
import pytest

pytest.importorskip("tflite")
pytest.importorskip("onnxruntime")
face_mesh = pytest.importorskip("mediapipe.python.solutions.face_mesh")

import cv2  # noqa: E402

from facesynth.web import convert, track  # noqa: E402

N_FRAMES = 20


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return convert.convert_all(tmp_path_factory.mktemp("tracker"))


@pytest.fixture(scope="module")
def frames(shared_clip_dir):
    cap = cv2.VideoCapture(str(shared_clip_dir("lp_d3") / "video.mp4"))
    out = []
    for _ in range(N_FRAMES):
        ok, bgr = cap.read()
        assert ok
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return out


def _mediapipe(frames, refine):
    fm = face_mesh.FaceMesh(static_image_mode=False, max_num_faces=1, refine_landmarks=refine)
    out = []
    for rgb in frames:
        lm = fm.process(rgb).multi_face_landmarks[0].landmark
        h, w = rgb.shape[:2]
        out.append(np.array([(p.x * w - 0.5, p.y * h - 0.5) for p in lm], np.float32))
    fm.close()
    return out


def test_converted_graphs_shapes(models):
    import onnxruntime as ort

    want = {"face_detection": [(1, 896, 16), (1, 896, 1)], "face_landmark": [(1, 478, 2), (1, 1, 1, 1)]}
    assert set(models) == set(want)
    for name, path in models.items():
        s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        h = {"face_detection": 128, "face_landmark": 192}[name]
        x = np.random.default_rng(0).random((2, h, h, 3), dtype=np.float32)
        one = s.run(None, {"input": x[:1]})
        assert [o.shape for o in one] == want[name]
        two = s.run(None, {"input": x})  # any batch: row 0 of a batch of 2 is the batch of 1
        for a, b in zip(one, two, strict=True):
            np.testing.assert_allclose(b[:1], a, rtol=1e-4, atol=1e-4)


def test_mesh_matches_mediapipe_same_model(models, frames):
    """The converted attention mesh, its custom ops and refinement included, cropped where
    MediaPipe's own tracking crops it (from its previous frame's points), gives MediaPipe's
    ``refine_landmarks=True`` points: the same .tflite, so well under a pixel, lips, eyes and
    irises (the refined parts) as well as the rest."""
    ref = _mediapipe(frames, refine=True)
    tr = track.OnnxFaceTracker(next(iter(models.values())).parent)
    err = []
    for i in range(1, len(frames)):
        roi = track.roi_from_points(ref[i - 1], 33, 263, track.FACE_SCALE)
        err.append(np.linalg.norm(tr.mesh_points(frames[i], roi) - ref[i], axis=1))
    err = np.array(err)
    # measured 0.45 px (lips 0.50, eyes 0.19-0.24, irises 0.10-0.15); sampling the crop without
    # MediaPipe's half-pixel shift (track._crop) gives 0.79
    assert np.median(err) < 0.7, np.median(err)
    for name, rows in _refined_rows().items():
        assert np.median(err[:, rows]) < 0.7, (name, np.median(err[:, rows]))
    assert np.abs(np.median(err, axis=0)).max() < 4.0


def _refined_rows() -> dict[str, np.ndarray]:
    """Which of the 478 points each refinement (lips, eyes, irises) writes."""
    from facesynth.web import mediapipe_ops

    table = mediapipe_ops.refinement_table()
    bounds = np.cumsum([0, 468, 80, 71, 71, 5, 5])
    return {name: np.flatnonzero((table >= lo) & (table < hi))
            for name, lo, hi in zip(mediapipe_ops.REFINE_STREAMS[1:], bounds[1:-1], bounds[2:], strict=True)}


def test_refinement_table_covers_the_478_points():
    """Read from the wheel: the mesh first, every point written, lips 80, eyes 71 each, irises 468-477."""
    rows = _refined_rows()
    assert [len(r) for r in rows.values()] == [80, 71, 71, 5, 5]
    assert list(rows["left_iris"]) == [468, 469, 470, 471, 472]
    assert list(rows["right_iris"]) == [473, 474, 475, 476, 477]
    assert not set(rows["left_eye"]) & set(rows["right_eye"])


def test_tracker_agrees_with_ingest_landmarker(models, frames):
    """The whole tracker (detector, then tracking on its own points) against ``facesynth ingest
    --landmarker mediapipe`` (refine_landmarks=True): the same attention mesh, so within the
    2 px the page promises, everywhere and on the irises."""
    ref = _mediapipe(frames, refine=True)
    tr = track.OnnxFaceTracker(next(iter(models.values())).parent)
    got = [tr.track(rgb) for rgb in frames]
    assert all(g is not None and g.shape == (478, 2) and g.dtype == np.float32 for g in got)
    err = np.linalg.norm(np.array(got) - np.array(ref), axis=2)
    assert np.median(err[:, 468:]) < 2.0, np.median(err[:, 468:])  # irises
    assert np.median(err) < 2.0, np.median(err)
