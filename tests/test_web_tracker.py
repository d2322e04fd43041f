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


class _Op:
    """A stand-in TFLite operator: tensor indices in and out."""

    def __init__(self, ins, outs):
        self.ins, self.outs = ins, outs

    def Inputs(self, k):  # noqa: N802 - tflite's API
        return self.ins[k]

    def Outputs(self, k):  # noqa: N802
        return self.outs[k]


class _Graph:
    """The converter's surface that facesynth.web.mediapipe_ops writes into."""

    def __init__(self, shapes, nchw=()):
        self.name, self.nodes, self.inits, self.shapes, self.nchw = "test", [], [], shapes, set(nchw)

    def tname(self, i):
        return f"t{i}"

    def shape(self, i):
        return self.shapes[i]

    def init(self, name, arr):
        from onnx import numpy_helper

        self.inits.append(numpy_helper.from_array(np.asarray(arr, order="C"), name))
        return name

    def node(self, op, ins, outs, **attrs):
        from onnx import helper

        self.nodes.append(helper.make_node(op, ins, outs, **attrs))

    def run(self, feeds: dict, out: str):
        import onnxruntime as ort
        from onnx import TensorProto, helper

        g = helper.make_graph(self.nodes, "g", [helper.make_tensor_value_info(k, TensorProto.FLOAT, v.shape) for k, v in feeds.items()],
                              [helper.make_tensor_value_info(out, TensorProto.FLOAT, None)], self.inits)
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", convert.OPSET)])
        m.ir_version = 8
        return ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(None, feeds)[0]


def test_landmarks_to_matrix_is_mediapipes_product_of_four():
    """Against MediaPipe's own formulation: shift(centre) rot(-r) scale shift(-out / 2), 4 x 4 products."""
    from facesynth.web import mediapipe_ops

    rng = np.random.default_rng(0)
    pts = (rng.random((1, 30, 3)) * 100).astype(np.float32)
    opts = {"left_rotation_idx": 3, "right_rotation_idx": 17, "subset_idxs": [[1, 2], [5, 9], [20, 28]],
            "output_width": 16, "output_height": 12, "scale_x": 1.5, "scale_y": 1.25, "target_rotation_radians": 0.3}
    g = _Graph({0: [1, 30, 3]})
    mediapipe_ops.landmarks_to_matrix(g, _Op([0], [1]), opts)
    got = g.run({"t0": pts}, "t1")[0]
    p = pts[0, :, :2].astype(np.float64)
    d = p[17] - p[3]
    r = opts["target_rotation_radians"] - np.arctan2(d[1], d[0])
    rot = lambda a: np.array([[np.cos(a), -np.sin(a), 0, 0], [np.sin(a), np.cos(a), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # noqa: E731
    sub = p[[1, 2, 5, 9, 20, 28]] @ rot(r)[:2, :2].T
    lo, hi = sub.min(0), sub.max(0)
    centre = rot(-r)[:2, :2] @ ((lo + hi) / 2)
    shift = lambda x, y: np.array([[1, 0, 0, x], [0, 1, 0, y], [0, 0, 1, 0], [0, 0, 0, 1]])  # noqa: E731
    scale = np.diag([1.5 * (hi - lo)[0] / 16, 1.25 * (hi - lo)[1] / 12, 1, 1])
    want = shift(*centre) @ rot(-r) @ scale @ shift(-8, -6)
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_transform_tensor_bilinear_is_mediapipes_loop():
    """Against MediaPipe's per-pixel loop (v2: half-pixel shift, zero outside [0, W-1] x [0, H-1])."""
    from facesynth.web import mediapipe_ops

    rng = np.random.default_rng(1)
    feat = rng.random((1, 4, 10, 12)).astype(np.float32)  # NCHW, as the converter holds feature maps
    m = np.eye(4, dtype=np.float32)
    m[:2, :2] = [[0.9, -0.3], [0.25, 0.8]]
    m[:2, 3] = [1.73, -0.41]  # some samples fall outside (none on the border): the zero rule is exercised
    g = _Graph({0: [1, 10, 12, 4], 1: [1, 4, 4]}, nchw={0})
    mediapipe_ops.transform_tensor_bilinear(g, _Op([0, 1], [2]), {"output_height": 7, "output_width": 9})
    got = g.run({"t0": feat, "t1": m[None]}, "t2")[0]  # (C, 7, 9)
    x_t, y_t = m[0].astype(np.float64).copy(), m[1].astype(np.float64).copy()
    x_t[3] += x_t[0] * 0.5 + x_t[1] * 0.5 - 0.5
    y_t[3] += y_t[0] * 0.5 + y_t[1] * 0.5 - 0.5
    want = np.zeros((4, 7, 9))
    for v in range(7):
        for u in range(9):
            x, y = x_t[0] * u + x_t[1] * v + x_t[3], y_t[0] * u + y_t[1] * v + y_t[3]
            if x < 0 or x > 11 or y < 0 or y > 9:
                continue
            x0, y0 = int(np.floor(x)), int(np.floor(y))
            read = lambda yy, xx: feat[0, :, yy, xx] if yy < 10 and xx < 12 else 0.0  # noqa: E731
            fx, fy = x - x0, y - y0
            top = (1 - fx) * read(y0, x0) + fx * read(y0, x0 + 1)
            bottom = (1 - fx) * read(y0 + 1, x0) + fx * read(y0 + 1, x0 + 1)
            want[:, v, u] = fy * bottom + (1 - fy) * top
    assert (want == 0).all(axis=0).any() and not (want == 0).all()
    np.testing.assert_allclose(got, want, atol=1e-5)
