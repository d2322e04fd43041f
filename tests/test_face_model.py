import json

import numpy as np
import pytest
from _faces import face_sequence_arrays

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from facesynth.errors import FacesynthError
from facesynth.metrics import psnr
from facesynth.model import FaceModel, FaceModelConfig, load_face_model, save_face_model
from facesynth.model.artifact import MANIFEST


@pytest.fixture(scope="module")
def seq():
    frames, lm = face_sequence_arrays(n=16)
    return FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")


@pytest.fixture(scope="module")
def model(seq):
    return FaceModel.fit(seq, FaceModelConfig(reference_width=64, appearance_variance=0.95), progress=False)


def test_fit_shapes_and_variance(model, seq):
    d = model.describe()
    assert d["appearance_variance_kept"] >= 0.95 and d["shape_variance_kept"] >= 0.98
    tex = model.sample_textures(seq)
    assert tex.shape == (len(seq), 3 * model.n_pixels) and tex.dtype == np.float32
    assert 0 <= tex.min() and tex.max() <= 1
    # training textures: reconstruction error equals the discarded eigenvalues' sum
    full = FaceModel.fit(seq, FaceModelConfig(reference_width=64, appearance_variance=1.0), progress=False)
    k = model.appearance_pca.n_components
    rec = full.appearance_pca.truncate(k)
    resid = ((tex - rec.reconstruct(rec.project(tex))) ** 2).sum() / (len(tex) - 1)
    np.testing.assert_allclose(resid, full.appearance_pca.eigenvalues[k:].sum(), rtol=1e-3)


def test_shape_params_invariant_to_similarity(model, seq):
    lm = seq.landmarks[:4]
    c, s = np.cos(0.3) * 1.7, np.sin(0.3) * 1.7
    moved = lm @ np.array([[c, -s], [s, c]]).T + [40, -7]
    np.testing.assert_allclose(model.shape_params(moved), model.shape_params(lm), atol=1e-5)


def test_render_reproduces_training_frame(model, seq):
    """A frame's own texture rendered back at its own landmarks gives back the frame."""
    import cv2

    rows = [3]
    tex = model.sample_textures(seq, rows)
    crop, mask, place = model.render(tex, seq.landmarks[rows])
    frame = seq.frame(3).astype(np.float32) / 255
    h, w = frame.shape[:2]
    out = cv2.warpAffine(crop[0], place[0], (w, h), flags=cv2.INTER_LINEAR)
    m = cv2.warpAffine(mask[0], place[0], (w, h)) > 0.999
    m = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert m.sum() > 1000
    assert psnr(out, frame, m, peak=1.0) > 30


def test_artifact_round_trip(model, seq, tmp_path):
    save_face_model(model, tmp_path / "m")
    back = load_face_model(tmp_path / "m")
    np.testing.assert_array_equal(back.shape_params(seq.landmarks), model.shape_params(seq.landmarks))
    tex = model.sample_textures(seq, [0, 1])
    np.testing.assert_array_equal(back.appearance_params(tex), model.appearance_params(tex))
    np.testing.assert_array_equal(back.span, model.span)
    manifest = json.loads((tmp_path / "m" / MANIFEST).read_text())
    assert manifest["data_fingerprint"] == seq.fingerprint
    assert "torch" in manifest["packages"] and manifest["config"]["reference_width"] == 64


def test_incompatible_artifact_is_refused(model, tmp_path):
    save_face_model(model, tmp_path / "m")
    p = tmp_path / "m" / MANIFEST
    manifest = json.loads(p.read_text())
    manifest["format_version"] = 99
    p.write_text(json.dumps(manifest))
    with pytest.raises(FacesynthError, match="format version 99.*not supported"):
        load_face_model(tmp_path / "m")
    with pytest.raises(FacesynthError, match="not a face model directory"):
        load_face_model(tmp_path)


def test_wrong_landmarks_are_errors(model):
    with pytest.raises(FacesynthError, match=r"\(N, 68, 2\)"):
        model.shape_params(np.zeros((2, 5, 2), np.float32))
    bad = np.zeros((1, 68, 2), np.float32)
    bad[0, 3, 1] = np.nan
    with pytest.raises(FacesynthError, match="NaN"):
        model.shape_params(bad)


def test_too_few_frames(seq):
    with pytest.raises(FacesynthError, match="at least 3 frames"):
        FaceModel.fit(seq, rows=[0, 1])
