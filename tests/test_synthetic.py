"""The embedded synthetic subject: determinism, landmark semantics, and a real
dependence of appearance on shape (measured on the rendered pixels)."""

import cv2
import numpy as np
import pytest

from facesynth.data import FaceSequence, make_synthetic_sequence
from facesynth.data.synthetic import CONTROL_NAMES, render_faces, synthetic_landmarks
from facesynth.data.synthetic_shape import MIRROR, RIGID, estimate_pose_and_controls, pose_matrices
from facesynth.errors import FacesynthError

SIZE = 128


@pytest.fixture(scope="module")
def seq() -> FaceSequence:
    return make_synthetic_sequence(n_frames=300, size=SIZE, seed=0)


def _gray(seq):
    return seq.load_frames().astype(np.float32).mean(-1)


def test_shapes_dtypes_bounds_and_meta(seq):
    assert len(seq) == 300 and seq.image_size == (SIZE, SIZE)
    assert seq.landmarks.dtype == np.float32 and seq.landmarks.shape == (300, 68, 2)
    assert np.isfinite(seq.landmarks).all()
    assert (seq.landmarks > 2).all() and (seq.landmarks < SIZE - 3).all()
    frames = seq.load_frames()
    assert frames.dtype == np.uint8 and frames.shape == (300, SIZE, SIZE, 3)
    c = seq.meta["controls"]
    assert seq.meta["control_names"] == list(CONTROL_NAMES) and c.shape == (300, len(CONTROL_NAMES))
    assert np.isfinite(c).all() and c.min() >= 0 and c.max() <= 1
    # every control is exercised: near-neutral frames and strong expressions both occur
    assert ((c > 0.6).mean(0) > 0.02).all() and ((c < 0.05).mean(0) > 0.2).all()
    assert seq.meta["synthetic"] is True and seq.meta["dropped_frames"] == 0


def test_deterministic_in_seed():
    a = make_synthetic_sequence(12, 96, seed=3)
    b = make_synthetic_sequence(12, 96, seed=3)
    c = make_synthetic_sequence(12, 96, seed=4)
    np.testing.assert_array_equal(a.load_frames(), b.load_frames())
    np.testing.assert_array_equal(a.landmarks, b.landmarks)
    assert not np.array_equal(a.landmarks, c.landmarks)
    assert np.abs(a.load_frames().astype(int) - c.load_frames().astype(int)).mean() > 1.0


def test_mean_face_is_symmetric_and_in_ibug_order():
    lm = synthetic_landmarks(np.zeros((1, 4)), size=200)[0]
    mirrored = lm[MIRROR] * [-1, 1] + [2 * lm[:, 0].mean(), 0]
    np.testing.assert_allclose(mirrored, lm, atol=1e-3)
    # iBUG semantics: brows above eyes above nose tip above mouth above chin
    assert lm[17:27, 1].max() < lm[36:48, 1].min() < lm[30, 1] < lm[48:68, 1].min() < lm[8, 1]
    assert lm[36, 0] < lm[39, 0] < lm[42, 0] < lm[45, 0]  # subject's right eye on image left


def test_pose_matches_opencv_similarity_and_controls_recovered(rng):
    controls = rng.uniform(0, 1, (20, 4))
    pose = rng.uniform(-1, 1, (20, 4)) * [0.03, 0.03, 4.0, 0.04]
    lm = synthetic_landmarks(controls, pose, size=SIZE)
    m, est = estimate_pose_and_controls(lm)
    np.testing.assert_allclose(est, controls, atol=1e-4)
    np.testing.assert_allclose(m, pose_matrices(pose, SIZE), atol=1e-3)
    # independent reference: OpenCV's similarity fit on the rigid points
    from facesynth.data.synthetic_shape import MEAN_SHAPE
    for t in range(3):
        ref, _ = cv2.estimateAffinePartial2D(MEAN_SHAPE[RIGID].astype(np.float32), lm[t, RIGID], method=cv2.LMEDS)
        np.testing.assert_allclose(m[t], ref, atol=2e-2)


def test_landmarks_follow_controls():
    eye, jaw, smile, brow = (np.eye(4)[[0, k]] * [[0], [1]] for k in (3, 0, 1, 2))  # rows: neutral, control k at 1

    def ear(p):  # eye aspect ratio (Soukupova & Cech 2016), right eye
        return (np.linalg.norm(p[37] - p[41]) + np.linalg.norm(p[38] - p[40])) / (2 * np.linalg.norm(p[36] - p[39]))

    e = synthetic_landmarks(eye)
    assert ear(e[1]) < 0.1 * ear(e[0])
    j = synthetic_landmarks(jaw)
    assert j[1, 66, 1] - j[1, 62, 1] > 15 and abs(j[0, 66, 1] - j[0, 62, 1]) < 0.5
    s = synthetic_landmarks(smile)
    assert s[1, 54, 0] - s[1, 48, 0] > s[0, 54, 0] - s[0, 48, 0] + 10 and s[1, 48, 1] < s[0, 48, 1]
    b = synthetic_landmarks(brow)
    assert (b[1, 17:27, 1] < b[0, 17:27, 1] - 5).all()


def _patch_mean(frames, cx, cy, hw, hh):
    return np.array([f[int(y - hh):int(y + hh) + 1, int(x - hw):int(x + hw) + 1].mean()
                     for f, x, y in zip(frames, cx, cy, strict=True)])


def test_forehead_darkens_with_brow_raise(seq):
    g, L, c = _gray(seq), seq.landmarks, seq.meta["controls"]
    iod = np.linalg.norm(L[:, 45] - L[:, 36], axis=1).mean()
    mid = 0.5 * (L[:, 36] + L[:, 45])  # rigid points: the patch does not follow the brows
    fh = _patch_mean(g, mid[:, 0], mid[:, 1] - 0.5 * iod, 0.35 * iod, 0.07 * iod)
    assert np.corrcoef(fh, c[:, CONTROL_NAMES.index("brow_raise")])[0, 1] < -0.9


def test_mouth_darkens_when_jaw_opens(seq):
    g, L, c = _gray(seq), seq.landmarks, seq.meta["controls"]
    cx, cy = 0.5 * (L[:, 48, 0] + L[:, 54, 0]), 0.5 * (L[:, 51, 1] + L[:, 57, 1])
    hw, hh = 0.5 * (L[:, 54, 0] - L[:, 48, 0]), 0.5 * (L[:, 57, 1] - L[:, 51, 1])
    dark = np.array([(f[int(y - b):int(y + b) + 1, int(x - a):int(x + a) + 1] < 50).mean()
                     for f, x, y, a, b in zip(g, cx, cy, hw, hh, strict=True)])
    jaw = c[:, CONTROL_NAMES.index("jaw_open")]
    assert np.corrcoef(dark, jaw)[0, 1] > 0.7
    assert dark[jaw > 0.8].mean() > 2 * dark[jaw < 0.05].mean()


def test_eye_region_changes_when_eyes_close(seq):
    g, L, c = _gray(seq), seq.landmarks, seq.meta["controls"]
    iod = np.linalg.norm(L[:, 45] - L[:, 36], axis=1).mean()
    close = c[:, CONTROL_NAMES.index("eye_close")]
    for a, b in ((36, 39), (42, 45)):
        ctr = 0.5 * (L[:, a] + L[:, b])
        hw, hh = 0.2 * iod, 0.12 * iod
        # contrast of the eye region (sclera vs iris): the lid covers both as the eye closes
        contrast = np.array([f[int(y - hh):int(y + hh) + 1, int(x - hw):int(x + hw) + 1].std() for f, (x, y) in zip(g, ctr, strict=True)])
        assert np.corrcoef(contrast, close)[0, 1] < -0.75


def test_smile_folds_and_cheeks_from_rendering_alone():
    # Same pose, noise off: only the smile control differs -> pixels change in the
    # nasolabial/cheek area beyond the mouth polygon, and rendering is a pure function of landmarks.
    ctrl = np.eye(4)[[0, 1]] * [[0], [1]]  # rows: neutral, smile at 1
    lm = synthetic_landmarks(ctrl, size=SIZE)
    img = render_faces(lm, SIZE, noise_sigma=0).astype(np.float32).mean(-1)
    again = render_faces(lm[1:], SIZE, seed=9, noise_sigma=0)
    np.testing.assert_array_equal(render_faces(lm[1:], SIZE, noise_sigma=0), again)
    mouth = np.zeros((SIZE, SIZE), np.uint8)
    for p in lm:
        cv2.fillPoly(mouth, [np.round(p[48:60]).astype(np.int32)], 1)
    mouth = cv2.dilate(mouth, np.ones((5, 5), np.uint8)).astype(bool)
    cheek_rows = slice(int(lm[0, 30, 1]), int(lm[0, 8, 1] - 5))
    diff = np.abs(img[1] - img[0])[cheek_rows] * ~mouth[cheek_rows]
    assert (diff > 8).sum() > 30


def test_bad_arguments_are_clear_errors():
    with pytest.raises(FacesynthError, match=r"controls must have shape \(T, 4\)"):
        synthetic_landmarks(np.zeros((3, 2)))
    with pytest.raises(FacesynthError, match="n_frames"):
        make_synthetic_sequence(0)
