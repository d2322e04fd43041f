"""SADM's gaze path (facesynth.sadm.gaze) and the ``ibug68+iris`` scheme: features against an
independent per-eye computation, the ridge against scikit-learn, a gaze-dependent appearance
recovered where the shape-only regressor cannot, save/load, compression, ONNX parity."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _faces import face_sequence_arrays

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from facesynth.data.iris import add_irises, combine_landmarks
from facesynth.data.readers import load_sequence
from facesynth.errors import FacesynthError
from facesynth.landmarks import IBUG68_IRIS, MEDIAPIPE478, get_scheme, scheme_for_points
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.sadm.fit import SADMConfig, fit_sadm, load_sadm, save_sadm
from facesynth.sadm.gaze import GazePath, expand, gaze_features, ridge_fit


def _with_irises(lm68: np.ndarray, gaze: np.ndarray) -> np.ndarray:
    """(N, 68, 2) + per-frame gaze (N, 2) (x, y in eye-width units) -> (N, 78, 2): each iris
    centre at its eye's corner midpoint moved by gaze along / across the corner axis, with 4
    boundary points around it."""
    out = []
    for corners in ((36, 39), (42, 45)):
        a, b = lm68[:, corners[0]].astype(np.float64), lm68[:, corners[1]].astype(np.float64)
        e = b - a
        perp = np.stack([-e[:, 1], e[:, 0]], 1)
        c = 0.5 * (a + b) + gaze[:, :1] * e + gaze[:, 1:] * perp
        r = 0.15 * np.linalg.norm(e, axis=1, keepdims=True)
        ring = [c + r * np.array(d) for d in ((1, 0), (0, -1), (-1, 0), (0, 1))]
        out.append(np.stack([c] + ring, 1))
    return np.concatenate([lm68] + out, 1).astype(np.float32)


def _reference_features(lm: np.ndarray, scheme) -> np.ndarray:
    """Per frame and eye, by rotation angle (atan2) and an explicit 2x2 rotation: the iris
    centre in the eye's frame (origin at the corners' midpoint, x towards the image-right
    corner, y its +90 degree turn), divided by the corner distance."""
    c = scheme.region("eye_corners")
    eyes = ((c[0], c[1]), (c[2], c[3]))
    centres = scheme.region("iris_centres")
    out = np.zeros((len(lm), 4))
    for n, frame in enumerate(np.asarray(lm, np.float64)):
        for k, ((ia, ib), ic) in enumerate(zip(eyes, centres, strict=True)):
            a, b = frame[ia], frame[ib]
            ang = np.arctan2(b[1] - a[1], b[0] - a[0])
            rot = np.array([[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])  # rotates by -ang
            out[n, 2 * k: 2 * k + 2] = rot @ (frame[ic] - (a + b) / 2) / np.linalg.norm(b - a)
    return out


def test_scheme_layout():
    s = get_scheme("ibug68+iris")
    assert s is IBUG68_IRIS and s.n_points == 78 and scheme_for_points(78) is s and s.base_scheme().name == "ibug68"
    assert s.region("right_iris").tolist() == list(range(68, 73)) and s.region("iris_centres").tolist() == [68, 73]
    assert s.region("eyes").tolist() == list(range(36, 48))
    lm = np.random.default_rng(0).normal(size=(3, 78, 2)).astype(np.float32)
    np.testing.assert_array_equal(s.to_ibug68(lm), lm[:, :68])


def test_combine_landmarks_layout_and_missing_rows(tmp_path):
    rng = np.random.default_rng(1)
    d, m = rng.uniform(0, 100, (4, 68, 2)).astype(np.float32), rng.uniform(0, 100, (4, 478, 2)).astype(np.float32)
    d[1], m[2] = np.nan, np.nan
    out = combine_landmarks(d, m)
    np.testing.assert_array_equal(out[[0, 3], :68], d[[0, 3]])
    np.testing.assert_array_equal(out[[0, 3], 68:], m[[0, 3]][:, MEDIAPIPE478.region("irises")])
    assert np.isnan(out[1]).all() and np.isnan(out[2]).all()
    with pytest.raises(FacesynthError, match="same frames"):
        combine_landmarks(d, m[:3])
    for name, arr in (("dlib", d), ("mp", m)):
        (tmp_path / name).mkdir()
        np.save(tmp_path / name / "landmarks.npy", arr)
    seq = add_irises(tmp_path / "dlib", tmp_path / "mp", tmp_path / "out")
    assert seq.scheme == "ibug68+iris" and len(seq) == 2
    assert json.loads((tmp_path / "out" / "meta.json").read_text())["landmarks"]["scheme"] == "ibug68+iris"
    assert load_sequence(tmp_path / "out", scheme="ibug68").landmarks.shape == (2, 68, 2)
    with pytest.raises(FacesynthError, match="expected ibug68"):
        add_irises(tmp_path / "mp", tmp_path / "mp", tmp_path / "bad")


def test_gaze_features_against_per_eye_rotation_and_similarity_invariance():
    rng = np.random.default_rng(2)
    _, lm68 = face_sequence_arrays(n=8, seed=3)
    lm = _with_irises(lm68, rng.uniform(-0.2, 0.2, (8, 2)))
    got = gaze_features(IBUG68_IRIS, lm)
    np.testing.assert_allclose(got, _reference_features(lm, IBUG68_IRIS), atol=1e-6)
    ang, s, t = 0.4, 1.7, np.array([30.0, -12.0])
    rot = s * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    np.testing.assert_allclose(gaze_features(IBUG68_IRIS, lm.astype(np.float64) @ rot.T + t), got, atol=1e-6)
    # the same eye/iris geometry in MediaPipe's indices gives the same numbers
    mp = np.zeros((8, 478, 2))
    mp[:, MEDIAPIPE478.region("eye_corners")] = lm[:, [36, 39, 42, 45]]
    mp[:, MEDIAPIPE478.region("iris_centres")] = lm[:, [68, 73]]
    np.testing.assert_allclose(gaze_features(MEDIAPIPE478, mp), got, atol=1e-6)
    assert expand(got).shape == (8, 14)


def test_ridge_matches_scikit_learn():
    from sklearn.linear_model import Ridge

    rng = np.random.default_rng(4)
    z, r = rng.normal(size=(60, 14)), rng.normal(size=(60, 5))
    w, b = ridge_fit(z, r, 3.0)
    ref = Ridge(alpha=3.0, fit_intercept=True).fit(z, r)
    np.testing.assert_allclose(w, ref.coef_.T, atol=1e-10)
    np.testing.assert_allclose(b, ref.intercept_, atol=1e-10)


def test_eyes_path_compact_correction_equals_dense():
    """An "eyes" path adds its correction from its nonzero columns only: the same texture as
    the dense ``texture + path(landmarks)``, bit-identical outside the eye columns; its state
    dict (the artifact) keeps the full-width weights, and a path rebuilt from it is the same."""
    rng = np.random.default_rng(7)
    e, k, b = 14, 600, 5
    cols = np.sort(rng.choice(k, 40, replace=False))
    w, bias = np.zeros((e, k)), np.zeros(k)
    w[:, cols], bias[cols] = rng.normal(size=(e, 40)), rng.normal(size=40)
    bias[cols[0]] = 0.0  # a column with weights but no bias is still an eye column
    t = torch.from_numpy
    path = GazePath(MEDIAPIPE478, t(rng.normal(size=e)), t(rng.uniform(0.5, 2.0, e)), t(w), t(bias), 0.1, "eyes")
    np.testing.assert_array_equal(path.eye_columns.numpy(), cols)
    assert set(path.state_dict()) == {"mu", "sd", "weight", "bias"}
    lm = rng.uniform(100, 300, (b, MEDIAPIPE478.n_points, 2)).astype(np.float32)
    tex = t(rng.uniform(0, 1, (b, k)).astype(np.float32))
    with torch.no_grad():
        dense = (tex + path(t(lm))).numpy()
        got = path.add_to(tex, t(lm)).numpy()
        again = GazePath.from_state(MEDIAPIPE478, path.state_dict(), 0.1, "eyes").add_to(tex, t(lm)).numpy()
    np.testing.assert_allclose(got, dense, rtol=1e-6, atol=1e-6)
    rest = np.setdiff1d(np.arange(k), cols)
    np.testing.assert_array_equal(got[:, rest], tex.numpy()[:, rest])
    assert np.abs(got[:, cols] - tex.numpy()[:, cols]).min() > 0
    np.testing.assert_array_equal(again, got)


@pytest.fixture(scope="module")
def gaze_data():
    return make_gaze_data()


def make_gaze_data():
    """A synthetic subject whose appearance (in the face model's PCA) is one term driven by
    the shape (the mouth opening, through b_s[0]) and one by gaze (g_x, drawn per frame
    independently of the 68 points): texture = mean + z(b_s0) d_1 + (g_x / 0.2) d_0."""
    n = 60
    frames, lm68 = face_sequence_arrays(n=n, seed=5)
    rng = np.random.default_rng(6)
    gaze = np.stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.05, 0.05, n)], 1)
    seq = FaceSequence.from_arrays(_with_irises(lm68, gaze), ArrayFrames(frames), name="gaze", scheme="ibug68+iris")
    tr, te = np.arange(45), np.arange(45, n)
    model = FaceModel.fit(seq.to_scheme("ibug68"), FaceModelConfig(reference_width=64), rows=tr, progress=False)
    pca = model.appearance_pca
    d0, d1 = (pca.components[i] * 1.5 * np.sqrt(pca.eigenvalues[i]) for i in (0, 1))
    bs = model.shape_params(lm68, clamp=True)[:, 0]
    tex = pca.mean + ((bs - bs.mean()) / bs.std())[:, None].clip(-1, 1) * d1 + (gaze[:, :1] / 0.2) * d0
    return seq, tr, te, model, tex.astype(np.float32), gaze


def test_gaze_path_recovers_gaze_dependent_appearance(gaze_data):
    seq, tr, te, model, tex, gaze = gaze_data
    y_te = model.appearance_params(tex[te])
    errs = {}
    for on, folds, mode in ((False, 5, "path"), (True, 5, "path"), (True, 0, "path"), (True, 5, "inside")):
        sadm = fit_sadm(model, seq, tr, tex[tr], "linear", {"ridge": 100.0},
                        SADMConfig(gaze=on, gaze_mode=mode, gaze_folds=folds, augment_copies=0, gaze_target="params"))
        assert (sadm.gaze is not None) == (on and mode == "path")
        errs[(on, folds) if mode == "path" else mode] = ((sadm.predict_params(seq.landmarks[te])[:, :2] - y_te[:, :2]) ** 2).mean(0)
    var = y_te[:, :2].var(0)
    assert errs[False, 5][0] > 0.5 * var[0]  # from the 68 points alone, the gaze term is not predictable
    assert errs[True, 5][0] < 0.1 * var[0]  # the gaze path recovers it
    assert max(errs[True, 5][1], errs[False, 5][1]) < 0.1 * var[1]  # the shape term: the main map, both ways
    # cross-fitted residuals beat in-sample ones (the main map absorbs part of the gaze term in-sample)
    assert errs[True, 5][0] < errs[True, 0][0]
    assert errs["inside"][0] < 0.1 * var[0]  # a linear main map with the gaze inputs recovers it too


def test_gaze_default_follows_scheme_and_errors(gaze_data):
    seq, tr, _, model, tex, _ = gaze_data
    default = fit_sadm(model, seq, tr, tex[tr], "linear", None, SADMConfig(augment_copies=0))
    n_shape = fit_sadm(model, seq, tr, tex[tr], "linear", None, SADMConfig(augment_copies=0, gaze=False)).features(
        seq.landmarks[:2]).shape[1]
    assert default.appearance().needs_landmarks
    assert default.features(seq.landmarks[:2]).shape[1] in (n_shape, n_shape + 4 * SADMConfig().gaze_copies)
    plain = seq.to_scheme("ibug68")
    off = fit_sadm(model, plain, tr, tex[tr], "linear", None, SADMConfig(augment_copies=0))
    assert off.gaze is None and not off.appearance().needs_landmarks
    with pytest.raises(FacesynthError, match="irises"):
        fit_sadm(model, plain, tr, tex[tr], "linear", None, SADMConfig(gaze=True))
    with pytest.raises(FacesynthError, match="gaze_mode"):
        fit_sadm(model, seq, tr, tex[tr], "linear", None, SADMConfig(gaze_mode="sideways"))


def test_save_load_compress_and_onnx_parity(gaze_data, tmp_path):
    import onnxruntime as ort

    from facesynth.contract import SYNTHESIS_INPUT
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.sadm.compress import compress_synthesizer

    seq, tr, te, model, tex, _ = gaze_data
    sadm = fit_sadm(model, seq, tr, tex[tr], "krr", None, SADMConfig(augment_copies=1, gaze_folds=3, gaze_mode="both"))
    assert sadm.gaze is not None and sadm.appearance().gaze_inputs is not None
    save_sadm(sadm, tmp_path / "run")
    meta = json.loads((tmp_path / "run" / "sadm" / "sadm.json").read_text())
    assert meta["landmark_scheme"] == "ibug68+iris" and meta["gaze"]["alpha"] == sadm.gaze.alpha
    back = load_sadm(tmp_path / "run")
    lm = seq.landmarks[te]
    np.testing.assert_allclose(back.predict_params(lm), sadm.predict_params(lm), atol=1e-5)
    syn = back.synthesizer()
    full, _ = compress_synthesizer(syn, seq.landmarks[tr], keep=int(model.appearance_pca.n_components))
    x = torch.from_numpy(lm[:4])
    with torch.no_grad():
        np.testing.assert_allclose(full.texture(x).numpy(), syn.texture(x).numpy(), atol=1e-5)
    small, _ = compress_synthesizer(syn, seq.landmarks[tr], keep=3)
    path = export_synthesizer(small, tmp_path / "g.onnx")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    crop, mask, place = sess.run(None, {SYNTHESIS_INPUT: lm[:5]})
    with torch.no_grad():
        t_crop, t_mask, t_place = small(torch.from_numpy(lm[:5]))
    assert sess.get_inputs()[0].shape[1:] == [78, 2]
    np.testing.assert_allclose(crop, t_crop.numpy(), atol=1e-4)
    np.testing.assert_allclose(place, t_place.numpy(), atol=1e-3)
    # the gaze path's texture correction is computed on its eye columns only: no (14, C M) weight in the graph
    import onnx

    graph = onnx.load(str(path)).graph
    shapes = [list(t.dims) for t in graph.initializer]
    shapes += [list(a.t.dims) for n in graph.node if n.op_type == "Constant" for a in n.attribute if a.name == "value"]
    n_eye = int(small.appearance.gaze.eye_columns.numel())
    assert [14, n_eye] in shapes and [14, int(small.appearance.mean.numel())] not in shapes
    # the exported graph reads the irises: moving them changes the crop
    moved = lm[:1].copy()
    moved[:, 68:] += np.float32([3.0, 0.0])
    assert np.abs(sess.run(None, {SYNTHESIS_INPUT: moved})[0] - crop[:1]).max() > 1e-3


def test_dlib_iris_ingest_keeps_dlib_points(shared_clip_dir, tmp_path):
    """``--landmarker dlib+iris`` on the first frames of lp_d6: points 0-67 are the shipped
    dlib landmarks, 68-77 MediaPipe's irises, inside their eyes (both extras needed)."""
    pytest.importorskip("mediapipe")
    pytest.importorskip("dlib")
    from facesynth.data.iris import ingest_dlib_iris

    clip = shared_clip_dir("lp_d6")
    seq = ingest_dlib_iris(clip / "video.mp4", tmp_path / "out", max_frames=5)
    assert seq.scheme == "ibug68+iris" and seq.landmarks.shape == (5, 78, 2)
    np.testing.assert_allclose(seq.landmarks[:, :68], np.load(clip / "landmarks.npy")[:5], atol=1.0)
    g = gaze_features(IBUG68_IRIS, seq.landmarks)
    assert np.abs(g).max() < 0.5  # each iris centre lies between its eye's corners
    with pytest.raises(FacesynthError, match="--copy"):
        ingest_dlib_iris(clip / "video.mp4", tmp_path / "x", copy=True)
