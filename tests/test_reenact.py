"""Reenactment (issue 13): retargeting against ERI's FAPs and closed forms, and one real
pair (lp_d10 driven by lp_d13) against the acceptance figures, through ONNX Runtime."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facesynth.errors import FacesynthError
from facesynth.faps import compute_faps
from facesynth.geometry import apply_affine, similarity_fit
from facesynth.neutral import select_neutral
from facesynth.retarget import Retargeter

ROOT = Path(__file__).resolve().parents[1]


def _faces():
    from _faces import face_sequence_arrays

    _, lm = face_sequence_arrays(n=12, seed=4)
    return lm.astype(np.float64)


def test_same_face_is_identity():
    lm = _faces()
    r = Retargeter(lm[0], lm[0])
    np.testing.assert_allclose(r(lm), lm.astype(np.float32), atol=1e-3)
    np.testing.assert_array_equal(Retargeter(lm[0], lm[1], motion="absolute")(lm), lm.astype(np.float32))


def test_head_motion_is_the_conjugated_similarity():
    lm = _faces()
    driver_n = lm[1]
    avatar = apply_affine(driver_n, np.array([[1.3, -0.3, 30.0], [0.3, 1.3, -10.0]]))  # the same face, elsewhere
    s = similarity_fit(driver_n[None], (driver_n * 0.9 + [5.0, 3.0])[None])[0]
    rot = np.array([[np.cos(0.2), -np.sin(0.2)], [np.sin(0.2), np.cos(0.2)]])
    s[:, :2] = rot @ s[:, :2]
    frame = apply_affine(driver_n, s)  # the neutral face, only moved
    out = Retargeter(avatar, driver_n)(frame)[0]
    c = similarity_fit(driver_n[None], avatar[None])[0]  # driver -> avatar
    expected = apply_affine(apply_affine(apply_affine(avatar, np.linalg.inv(np.vstack([c, [0, 0, 1]]))[:2]), s), c)
    np.testing.assert_allclose(out, expected, atol=1e-3)


@pytest.mark.parametrize("head_motion", [True, False])
def test_expression_carries_the_drivers_faps(head_motion):
    """ERI's FAPs (each in its own face's FAP units) of the retargeted avatar equal the
    driver's (with the head motion, as the app, and without, as ERI's transfer)."""
    lm = _faces()
    avatar = lm[2].copy()
    avatar[:, 0] = avatar[:, 0] * 1.2  # a wider face: other FAP units
    r = Retargeter(avatar, lm[0], head_motion=head_motion)
    f_driver = compute_faps(lm[1:], lm[0])
    f_avatar = compute_faps(r(lm[1:]), avatar)
    scale = np.abs(f_driver).max()
    assert scale > 50
    assert np.abs(f_avatar - f_driver).max() < 0.05 * scale


def test_bad_inputs():
    lm = _faces()
    with pytest.raises(FacesynthError, match="motion"):
        Retargeter(lm[0], lm[1], motion="sideways")
    with pytest.raises(FacesynthError, match="driver neutral"):
        Retargeter(lm[0], lm[1][:10])
    with pytest.raises(FacesynthError, match="driver landmarks"):
        Retargeter(lm[0], lm[1])(np.zeros((3, 10, 2)))


# ------------------------------------------------------------------ a real pair
@pytest.fixture(scope="module")
def avatar(shared_clip_dir, tmp_path_factory):
    """A small linear model of lp_d10 (every 3rd training frame) exported with its avatar metadata."""
    from _onnx_models import linear_avatar

    from facesynth.data import load_sequence, temporal_split
    from facesynth.onnx.synthesis import export_synthesizer

    seq = load_sequence(shared_clip_dir("lp_d10"))
    train, test = temporal_split(len(seq))
    syn, meta = linear_avatar(seq, train)
    path = tmp_path_factory.mktemp("reenact") / "lp_d10.onnx"
    export_synthesizer(syn, path, meta)
    return path, seq, train, test


def test_pair_meets_the_acceptance_figures(avatar, shared_clip_dir):
    from facesynth.data import load_sequence
    from facesynth.eval.reenact import pair_figures

    path, seq, train, _ = avatar
    driver = np.asarray(load_sequence(shared_clip_dir("lp_d13")).landmarks[::3], np.float32)
    f = pair_figures(path, driver, seq.landmarks[train])["figures"]
    assert f["coverage_min"] >= 0.99, f
    assert f["mouth_open_r"] >= 0.9, f
    assert f["eye_open_r"] >= 0.7, f
    assert f["shape_ratio_rel_diff"] <= 0.05, f
    assert f["shape_ratio_rel_diff"] < f["shape_ratio_rel_diff_absolute_motion"], f  # the driver's face is not copied


def test_self_driving_relative_matches_absolute(avatar):
    from facesynth.eval.reenact import self_driving_psnr
    from facesynth.runtime.renderer import read_metadata

    path, seq, _, test = avatar
    rows = test[::6]
    neutral = np.asarray(read_metadata(path)["avatar_neutral"], np.float32)
    res = self_driving_psnr(path, seq.landmarks[rows], seq.iter_frames(rows), neutral)
    assert res["psnr_absolute_db"] > 20, res
    assert abs(res["difference_db"]) <= 0.3, res


def test_reenactor_needs_no_look_ahead(avatar, shared_clip_dir):
    from facesynth.runtime import Reenactor

    path, *_ = avatar
    drv = np.load(shared_clip_dir("lp_d13") / "landmarks.npy")[:12]
    live = Reenactor(path, neutral_frames=5)
    outs = [live.step(lm)[1] for lm in drv]
    # after 5 frames the neutral is fixed: the same as giving it up front
    n5 = drv[:5][select_neutral(drv[:5])[0]]
    given = Reenactor(path, n5)
    for lm, out in zip(drv[5:], outs[5:], strict=True):
        np.testing.assert_allclose(given.retarget(lm), out, atol=1e-4)
    frame, _ = live.step(drv[0])
    assert frame.shape == live.background.shape and frame.dtype == np.uint8


def test_full_frame_moves_the_avatars_own_head(avatar):
    """The avatar's frame is warped with the face: at its own neutral the output is the still
    frame's composite; with the neutral moved by (12, -8) px the hair and forehead around the
    face are the still frame's moved by the same (no second face left behind)."""
    import cv2

    from facesynth.runtime import Reenactor
    from facesynth.runtime.renderer import read_metadata

    path, *_ = avatar
    n = np.asarray(read_metadata(path)["avatar_neutral"], np.float32)
    full, still = Reenactor(path, motion="absolute"), Reenactor(path, motion="absolute", full_frame=False)
    assert full.full_frame and not still.full_frame
    a, b = full.step(n)[0], still.step(n)[0]
    assert np.abs(a.astype(int) - b).max() <= 1
    moved = full.step(n + np.float32([12, -8]))[0]
    h, w = moved.shape[:2]
    hull = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(n + [12, -8]).astype(np.int32)), 1)
    band = (cv2.dilate(hull, np.ones((31, 31), np.uint8)) > 0) & (cv2.dilate(hull, np.ones((9, 9), np.uint8)) == 0)
    band[int(n[0, 1]) - 8:] = False  # above the ears: the neck follows the head only in part
    shifted = np.roll(full.avatar.background, (-8, 12), axis=(0, 1))
    assert band.sum() > 2000
    assert np.abs(moved.astype(int) - shifted)[band].max() <= 2


def test_the_export_carries_the_warps_learned_motion(avatar):
    """The model's metadata holds the motion learned from its training frames (one (share,
    parallax) pair per control point besides the landmarks), and the runtime's warp uses it."""
    from facesynth.runtime import Reenactor
    from facesynth.runtime.renderer import read_metadata

    path, *_ = avatar
    entry = read_metadata(path)["frame_motion"]
    warp = Reenactor(path).frame_warp
    assert entry["frames"] == 60 and entry["points_fitted"] > 20
    np.testing.assert_array_equal(warp.motion, np.asarray(entry["coefficients"]))
    assert warp.motion.shape == (len(warp.src) - warp.n_face, 2)
    assert not np.allclose(warp.motion, warp.prior())  # learned, not the prior
    # the ring's size chosen on 20 other training frames, among those that clear the face
    assert entry["validation_frames"] == 20 and warp.ring_scale == entry["ring_scale"]
    assert entry["ring_scores"][f"{warp.ring_scale:g}"] == max(v for v in entry["ring_scores"].values() if v is not None)


def test_app_says_when_a_model_predates_the_learned_warp_or_a_bound(avatar, shared_clip_dir, tmp_path):
    """A model whose metadata has no frame_motion, or whose shape_pca has no param_norm_max
    (exported before them), still renders the whole head (with the geometric rule, or without
    that bound), and the app names what is missing in one line; the current export warns of
    nothing."""
    import onnx

    path, *_ = avatar
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    pca = json.loads(meta["shape_pca"])
    assert pca["param_norm_max"] > 0

    def older(name, change):
        m = onnx.load(str(path))
        props = change(dict(meta))
        del m.metadata_props[:]
        for k, v in props.items():
            entry = m.metadata_props.add()
            entry.key, entry.value = k, v
        out = tmp_path / f"{name}.onnx"
        onnx.save(m, str(out))
        return out

    no_motion = older("no_motion", lambda d: {k: v for k, v in d.items() if k != "frame_motion"})
    no_bound = older("no_bound", lambda d: {**d, "shape_pca": json.dumps({k: v for k, v in pca.items() if k != "param_norm_max"})})
    clip = shared_clip_dir("lp_d13")
    for model, missing in ((path, None), (no_motion, "the learned full-frame warp"), (no_bound, "the expressions' bound")):
        out = tmp_path / f"{model.stem}.mp4"
        res = subprocess.run([sys.executable, "-m", "facesynth", "app", "--model", str(model), "--landmarks", str(clip),
                              "--out", str(out), "--max-frames", "3", "--no-progress"], capture_output=True, text=True, cwd=ROOT)
        assert res.returncode == 0, res.stderr
        warnings = [line for line in res.stderr.splitlines() if "exported by an older version" in line]
        if missing is None:
            assert not warnings, res.stderr
        else:
            assert len(warnings) == 1 and f"without {missing}: re-export it" in warnings[0], res.stderr


def test_app_writes_the_rendered_landmarks(avatar, shared_clip_dir, tmp_path):
    path, *_ = avatar
    clip = shared_clip_dir("lp_d13")
    out, lm_out = tmp_path / "out.mp4", tmp_path / "avatar.npy"
    cmd = [sys.executable, "-m", "facesynth", "app", "--model", str(path), "--landmarks", str(clip), "--out", str(out),
           "--max-frames", "8", "--side-by-side", "--save-landmarks", str(lm_out), "--no-progress", "--json"]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    saved = np.load(lm_out)
    assert saved.dtype == np.float32 and saved.shape == (8, 68, 2)
    assert summary["motion"] == "relative" and out.is_file()
    bad = subprocess.run(cmd[:-3] + ["--driver-neutral", "99999", "--no-progress"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "--driver-neutral" in bad.stderr


def test_shape_space_clamps_along_the_components_only():
    from facesynth.retarget import ShapeSpace

    rng = np.random.default_rng(0)
    mean = _faces()[0] - _faces()[0].mean(0)
    mean = (mean / np.linalg.norm(mean)).reshape(-1)
    comps = np.linalg.qr(rng.normal(size=(136, 3)))[0].T  # orthonormal rows
    comps -= np.outer(comps @ mean, mean)  # orthogonal to the mean (no scale change)
    comps = np.linalg.qr(comps.T)[0].T
    space = ShapeSpace(mean, comps, np.array([0.02, 0.01, 0.01]), keep_eyes=False)  # the eyelids: the next test
    frame = np.array([[2.0, -0.5, 100.0], [0.5, 2.0, 50.0]])  # model frame -> image frame
    inside = (mean + 0.5 * space.limit @ comps).reshape(68, 2)
    shape = apply_affine(inside, frame)
    np.testing.assert_allclose(space.project(shape), shape, atol=1e-9)  # inside the box: unchanged
    far = (mean + 10 * space.limit[0] * comps[0] + 0.001 * rng.normal(size=136)).reshape(68, 2)
    out = space.project(apply_affine(far, frame))
    m = mean.reshape(68, 2)
    back = apply_affine(out, similarity_fit(out[None], m[None])[0]).reshape(-1)  # the model frame, as the projection aligns
    b = (back - mean) @ comps.T
    before = (apply_affine(far, similarity_fit(far[None], m[None])[0]).reshape(-1) - mean) @ comps.T
    assert abs(before[0]) > 5 * space.limit[0]
    # one projection step: the similarity re-fit of the moved shape leaves it near the limit
    assert abs(b[0]) <= 1.5 * space.limit[0]


def test_shape_space_keeps_the_eyelids_relative_to_their_corners():
    from facesynth.landmarks import LEFT_EYE, RIGHT_EYE
    from facesynth.retarget import ShapeSpace

    rng = np.random.default_rng(1)
    mean = _faces()[0] - _faces()[0].mean(0)
    mean = (mean / np.linalg.norm(mean)).reshape(-1)
    comps = np.linalg.qr(rng.normal(size=(136, 3)))[0].T
    comps -= np.outer(comps @ mean, mean)
    comps = np.linalg.qr(comps.T)[0].T
    limit = np.array([0.02, 0.01, 0.01])
    wide = (mean + 10 * limit[0] * comps[0]).reshape(68, 2).copy()
    wide[[37, 38, 43, 44], 1] -= 0.02  # upper lids up: wider eyes than the model has seen
    wide[[40, 41, 46, 47], 1] += 0.02

    def local(shape, eye):  # the eye contour in the frame of its two corners (translation, rotation, scale removed)
        z = shape[list(eye), 0] + 1j * shape[list(eye), 1]
        return (z - z[0]) / (z[3] - z[0])

    kept = ShapeSpace(mean, comps, limit).project(wide)
    cut = ShapeSpace(mean, comps, limit, keep_eyes=False).project(wide)
    for eye in (RIGHT_EYE, LEFT_EYE):
        np.testing.assert_allclose(local(kept, eye), local(wide, eye), atol=1e-9)
        assert np.abs(local(cut, eye) - local(wide, eye)).max() > 1e-3  # without: the clamp moves the lids too
    others = [i for i in range(68) if i not in RIGHT_EYE + LEFT_EYE]
    np.testing.assert_allclose(kept[others], cut[others], atol=1e-12)  # the rest of the face is clamped alike


def _mouth_closing_case(turn: float):
    """A driver whose neutral mouth is open (inner lips 8 px apart) closes it, its head turned by
    ``turn`` rad; the avatar's neutral mouth is closed (1 px): the driver's displacement alone
    would put the avatar's lower inner lip above its upper one."""
    lm = _faces()
    up, lo = [61, 62, 63], [67, 66, 65]
    driver_n, avatar = lm[0].copy(), lm[1].copy()
    driver_n[lo, 1] = driver_n[up, 1] + 8.0
    avatar[lo, 1] = avatar[up, 1] + 1.0
    frame = driver_n.copy()
    frame[lo, 1] = frame[up, 1]  # closed
    c = frame.mean(0)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    return driver_n, avatar, (frame - c) @ rot.T + c, rot, up, lo


@pytest.mark.parametrize("turn", [0.0, 0.3])
def test_inner_lips_meet_instead_of_crossing(turn):
    """Facing inner-lip points that would cross meet at their midpoint (a closed mouth), along
    the avatar's down axis moved with the head; without that step they cross by ~6 px."""
    from facesynth.retarget import Retargeter

    driver_n, avatar, frame, rot, up, lo = _mouth_closing_case(turn)
    r = Retargeter(avatar, driver_n)
    out = r(frame[None])[0].astype(np.float64)
    down = rot @ r._down
    gap = (out[lo] - out[up]) @ down
    np.testing.assert_allclose(gap, 0.0, atol=1e-3)  # they meet
    naive = r._uncrossed
    r._uncrossed = lambda expr, d: expr  # the displacement alone
    crossed = r(frame[None])[0].astype(np.float64)
    r._uncrossed = naive
    assert ((crossed[lo] - crossed[up]) @ down).max() < -4.0


def test_the_graph_uncrosses_the_lips_as_numpy_does():
    """RetargetGraph (the talking-head file's retargeting) against Retargeter on the closing
    mouth, head turned, through a shape clamp that moves the mouth (step 5 uncrosses again)."""
    import torch

    from facesynth.onnx.retarget_graph import RetargetGraph
    from facesynth.retarget import Retargeter, ShapeSpace

    driver_n, avatar, frame, rot, up, lo = _mouth_closing_case(0.3)
    rng = np.random.default_rng(2)
    mean = avatar - avatar.mean(0)
    mean[lo, 1] = mean[up, 1] - 8.0  # a model whose mean mouth is folded
    mean = (mean / np.linalg.norm(mean)).reshape(-1)
    lips = np.zeros((68, 2))
    lips[lo, 1] = 1.0  # its first component opens the mouth, so clamping it folds the mouth again
    comps = np.c_[lips.reshape(-1), rng.normal(size=(136, 2))].T
    comps -= np.outer(comps @ mean, mean)
    comps = np.linalg.qr(comps.T)[0].T
    space = ShapeSpace(mean, comps, np.array([1e-4, 1e-4, 1e-4]))
    r = Retargeter(avatar, driver_n, shape_space=space)
    want = r(frame[None])[0]
    down = rot @ r._down
    np.testing.assert_allclose((want[lo] - want[up]) @ down, 0.0, atol=1e-3)
    r.shape_space = None
    clamped = space.project(r(frame[None])[0].astype(np.float64))
    assert ((clamped[lo] - clamped[up]) @ down).max() < -1.0  # the clamp alone crosses them
    g = RetargetGraph(avatar, space).eval()
    with torch.no_grad():
        got = g(torch.from_numpy(frame[None].astype(np.float32)), torch.from_numpy(driver_n.astype(np.float32)))[0].numpy()
    np.testing.assert_allclose(got, want, atol=0.02)


def _eye_case(turn: float = 0.3):
    """A shape space around face 0, and that face (turned by ``turn`` rad, scaled, moved) with
    its right eye opened to twice its gap and its left eye half-shut."""
    from facesynth.landmarks import RIGHT_EYE

    rng = np.random.default_rng(3)
    face = _faces()[0]
    mean = face - face.mean(0)
    mean = (mean / np.linalg.norm(mean)).reshape(-1)
    comps = np.linalg.qr(rng.normal(size=(136, 3)))[0].T
    comps -= np.outer(comps @ mean, mean)
    comps = np.linalg.qr(comps.T)[0].T
    shape = face.copy()
    mid = shape[list(RIGHT_EYE)].mean(0)
    shape[list(RIGHT_EYE), 1] = mid[1] + 2.0 * (shape[list(RIGHT_EYE), 1] - mid[1])  # right eye opened
    lmid = shape[[42, 45]].mean(0)
    shape[[43, 44, 46, 47], 1] = lmid[1] + 0.3 * (shape[[43, 44, 46, 47], 1] - lmid[1])  # left eye half-shut
    rot = 1.4 * np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    shape = shape @ rot.T + np.array([40.0, -25.0])
    return mean, comps, np.array([1.0, 1.0, 1.0]), shape  # wide limits: the clamp moves nothing


def test_an_eye_wider_than_the_avatars_widest_is_capped_there():
    """ShapeSpace.eye_open_max: an eye opened past its cap comes out exactly at the cap, its
    corners, its position along the corner line and the rest of the face unchanged; an eye
    below its cap (a half-shut one) is left alone."""
    from facesynth.landmarks import LEFT_EYE, RIGHT_EYE, eye_openings
    from facesynth.retarget import ShapeSpace

    mean, comps, limit, shape = _eye_case()
    free = ShapeSpace(mean, comps, limit).project(shape)
    np.testing.assert_allclose(free, shape, atol=1e-9)
    before = eye_openings(shape)
    cap = np.array([0.6 * before[0], 2.0 * before[1]])
    out = ShapeSpace(mean, comps, limit, eye_open_max=cap).project(shape)
    np.testing.assert_allclose(eye_openings(out), [cap[0], before[1]], rtol=1e-9)
    others = [i for i in range(68) if i not in RIGHT_EYE]
    np.testing.assert_allclose(out[others], shape[others], atol=1e-9)  # the left eye too (below its cap)
    axis = shape[39] - shape[36]
    axis /= np.linalg.norm(axis)
    np.testing.assert_allclose(out[list(RIGHT_EYE)] @ axis, shape[list(RIGHT_EYE)] @ axis, atol=1e-9)
    moved = np.linalg.norm(out - shape, axis=1)
    assert moved[[36, 39]].max() < 1e-9 and moved[list(RIGHT_EYE)].max() > 1.0
    assert set(LEFT_EYE).isdisjoint(np.flatnonzero(moved > 1e-9))


def test_the_eye_cap_round_trips_the_metadata_and_refuses_bad_values():
    from facesynth.errors import FacesynthError
    from facesynth.retarget import ShapeSpace

    mean, comps, limit, _ = _eye_case()
    space = ShapeSpace(mean, comps, limit, eye_open_max=np.array([0.31, 0.29]))
    back = ShapeSpace.from_dict(space.to_dict())
    np.testing.assert_allclose(back.eye_open_max, [0.31, 0.29])
    old = {k: v for k, v in space.to_dict().items() if k != "eye_open_max"}  # a file exported before the cap
    assert ShapeSpace.from_dict(old).eye_open_max is None
    for bad in ([0.3], [0.3, -1.0], [0.3, float("nan")]):
        with pytest.raises(FacesynthError, match="eye_open_max"):
            ShapeSpace.from_dict({**space.to_dict(), "eye_open_max": bad})


def test_the_graph_caps_the_eyes_as_numpy_does():
    """RetargetGraph with a capped shape space against Retargeter, the driver's right eye
    opened past the avatar's widest and its head turned."""
    import torch

    from facesynth.landmarks import eye_openings
    from facesynth.onnx.retarget_graph import RetargetGraph
    from facesynth.retarget import Retargeter, ShapeSpace

    mean, comps, limit, frame = _eye_case()
    avatar, driver_n = _faces()[1], _faces()[0] @ (1.4 * np.eye(2)) + np.array([40.0, -25.0])
    cap = 0.8 * eye_openings(avatar)
    space = ShapeSpace(mean, comps, limit, eye_open_max=cap)
    want = Retargeter(avatar, driver_n, shape_space=space)(frame[None])[0].astype(np.float64)
    uncapped = Retargeter(avatar, driver_n, shape_space=ShapeSpace(mean, comps, limit))(frame[None])[0]
    assert eye_openings(uncapped)[0] > 1.5 * cap[0]  # the driver's wide eye, unclamped
    np.testing.assert_allclose(eye_openings(want)[0], cap[0], rtol=1e-4)
    g = RetargetGraph(avatar, space).eval()
    with torch.no_grad():
        got = g(torch.from_numpy(frame[None].astype(np.float32)), torch.from_numpy(driver_n.astype(np.float32)))[0].numpy()
    np.testing.assert_allclose(got, want, atol=0.02)


def _residual_case():
    """A shape space around face 0 (three components, wide limits) and face 0 moved along a
    component and, across the span, along a smooth direction the components do not hold."""
    mean, comps, limit, _ = _eye_case()
    rng = np.random.default_rng(5)
    off = rng.normal(size=136)
    off -= comps.T @ (comps @ off)
    off -= mean * (mean @ off)
    off /= np.linalg.norm(off)
    return mean, comps, limit, off


def test_the_part_outside_the_components_is_scaled_down_to_residual_max():
    """ShapeSpace.residual_max: a shape whose out-of-span part is within it is projected as
    without it; one far beyond comes out with that part's norm at the cap (the residual of
    the result, re-aligned) and its in-span parameters unchanged; 0 puts it in the span."""
    from facesynth.retarget import ShapeSpace

    mean, comps, limit, off = _residual_case()
    frame = np.array([[1.3, -0.4, 60.0], [0.4, 1.3, 30.0]])
    free = ShapeSpace(mean, comps, limit, keep_eyes=False)
    inside = apply_affine((mean + 0.02 * comps[0] + 0.002 * off).reshape(68, 2), frame)
    small = free.norms(inside[None])[0][0]
    capped = ShapeSpace(mean, comps, limit, keep_eyes=False, residual_max=1.5 * small)
    np.testing.assert_allclose(capped.project(inside), free.project(inside), atol=1e-12)
    far = apply_affine((mean + 0.02 * comps[0] + 0.03 * off).reshape(68, 2), frame)
    big = free.norms(far[None])[0][0]
    assert big > 8 * small
    out = capped.project(far)
    # in the input's normalised frame (its similarity to the mean), the output keeps the input's
    # in-span parameters and its out-of-span part is the input's scaled to the cap
    mo, ca, sa, aligned, b, rest = capped._align(far)
    lin = np.array([[ca, -sa], [sa, ca]])
    back = ((out - mo) @ lin.T + capped._mu).reshape(-1)
    b_out = back @ comps.T - mean @ comps.T
    np.testing.assert_allclose(b_out, b, atol=1e-12)
    rest_out = back - mean - b_out @ comps
    np.testing.assert_allclose(rest_out, rest.reshape(-1) * (1.5 * small / big), atol=1e-12)
    flat = ShapeSpace(mean, comps, limit, keep_eyes=False, residual_max=0.0).project(far)
    back = ((flat - mo) @ lin.T + capped._mu).reshape(-1)
    np.testing.assert_allclose(back, mean + b @ comps, atol=1e-12)  # 0: in the span


def test_residual_max_round_trips_the_metadata_and_refuses_bad_values():
    from facesynth.errors import FacesynthError
    from facesynth.retarget import ShapeSpace

    mean, comps, limit, _ = _residual_case()
    space = ShapeSpace(mean, comps, limit, residual_max=0.0123)
    assert ShapeSpace.from_dict(space.to_dict()).residual_max == pytest.approx(0.0123)
    assert ShapeSpace.from_dict({k: v for k, v in space.to_dict().items() if k != "residual_max"}).residual_max is None
    for bad in (-1.0, float("inf")):
        with pytest.raises(FacesynthError, match="residual_max"):
            ShapeSpace.from_dict({**space.to_dict(), "residual_max": bad})


def test_the_graph_scales_the_residual_as_numpy_does():
    """RetargetGraph with residual_max (and the eye cap) against Retargeter: a driver whose
    face moves across the avatar's span, head turned."""
    import torch

    from facesynth.onnx.retarget_graph import RetargetGraph
    from facesynth.retarget import Retargeter, ShapeSpace

    mean, comps, limit, off = _residual_case()
    avatar = _faces()[1]
    driver_n = _faces()[0] * 1.4 + np.array([40.0, -25.0])
    frame = driver_n + 30.0 * off.reshape(68, 2)
    c = frame.mean(0)
    rot = np.array([[np.cos(0.2), -np.sin(0.2)], [np.sin(0.2), np.cos(0.2)]])
    frame = (frame - c) @ rot.T + c
    plain = ShapeSpace(mean, comps, limit)
    raw = Retargeter(avatar, driver_n, shape_space=plain)(frame[None])[0].astype(np.float64)
    rmax = 0.3 * plain.norms(raw[None])[0][0]
    space = ShapeSpace(mean, comps, limit, eye_open_max=np.array([0.5, 0.5]), residual_max=rmax)
    want = Retargeter(avatar, driver_n, shape_space=space)(frame[None])[0].astype(np.float64)
    assert np.abs(want - raw).max() > 1.0  # the cap moves the face
    g = RetargetGraph(avatar, space).eval()
    with torch.no_grad():
        got = g(torch.from_numpy(frame[None].astype(np.float32)), torch.from_numpy(driver_n.astype(np.float32)))[0].numpy()
    np.testing.assert_allclose(got, want, atol=0.02)


def test_the_components_parameters_are_scaled_into_the_avatars_ellipsoid():
    """ShapeSpace.param_norm_max: a shape whose clamped parameters (in units of the limits)
    are within the norm is projected as without it; one inside the box but beyond the norm
    comes out with its parameters scaled to that norm along their own direction (closed form)
    and its out-of-span part untouched; the box clamps first; norms measures it; the
    graph agrees; the metadata round-trips and bad values are refused."""
    import torch

    from facesynth.errors import FacesynthError
    from facesynth.onnx.retarget_graph import RetargetGraph
    from facesynth.retarget import ShapeSpace

    mean, comps, _, off = _residual_case()
    limit = np.array([0.05, 0.03, 0.02])
    frame = np.array([[390.0, -120.0, 260.0], [120.0, 390.0, 230.0]])  # a face about 400 px wide
    free = ShapeSpace(mean, comps, limit, keep_eyes=False)
    space = ShapeSpace(mean, comps, limit, keep_eyes=False, param_norm_max=1.0)

    def shape(b, rest=0.0):
        return apply_affine((mean + b @ comps + rest * off).reshape(68, 2), frame)

    inside = shape(np.array([0.6, 0.5, 0.4]) * limit, 0.002)  # norm about 0.88
    b_in = space._align(inside)[4]
    assert space.norms(inside[None])[1][0] == pytest.approx(np.linalg.norm(b_in / limit), rel=1e-12)
    assert np.linalg.norm(b_in / limit) < 0.9
    np.testing.assert_allclose(space.project(inside), free.project(inside), atol=1e-9)
    b = np.array([0.9, -0.8, 0.7]) * limit  # inside the box, norm 1.39
    far = shape(b, 0.002)
    np.testing.assert_allclose(free.project(far), far, atol=1e-9)  # the box alone keeps it
    out = space.project(far)
    mo, ca, sa, _, b_in, rest = space._align(far)
    lin = np.array([[ca, -sa], [sa, ca]])
    back = ((out - mo) @ lin.T + space._mu).reshape(-1)
    b_out = back @ comps.T - mean @ comps.T
    np.testing.assert_allclose(b_out, b_in / np.linalg.norm(b_in / limit), atol=1e-9)
    np.testing.assert_allclose(back - mean - b_out @ comps, rest.reshape(-1), atol=1e-9)  # out of span: as it was
    # measured again, the output is at the norm up to its re-alignment to the mean
    assert space.norms(out[None])[1][0] == pytest.approx(1.0, abs=0.01)
    # beyond the box: clamped to it first (norm sqrt(3)), then scaled to the norm
    wild = shape(np.array([3.0, 0.5, -2.0]) * limit)
    mo, ca, sa, _, b_w, _ = space._align(wild)
    back = ((space.project(wild) - mo) @ np.array([[ca, -sa], [sa, ca]]).T + space._mu).reshape(-1)
    box = np.clip(b_w, -limit, limit)
    assert np.abs(b_w).max() > 2 * limit[0] and np.linalg.norm(box / limit) > 1.4
    np.testing.assert_allclose(back @ comps.T - mean @ comps.T, box / np.linalg.norm(box / limit), atol=1e-9)
    # the graph, a driver retargeted through both
    avatar = apply_affine(mean.reshape(68, 2), frame)
    g = RetargetGraph(avatar, space).eval()
    want = Retargeter(avatar, avatar, shape_space=space).one(far)
    assert np.abs(want - Retargeter(avatar, avatar, shape_space=free).one(far)).max() > 0.5  # the bound moves the face
    with torch.no_grad():
        got = g(torch.from_numpy(far[None].astype(np.float32)), torch.from_numpy(avatar.astype(np.float32)))[0].numpy()
    np.testing.assert_allclose(got, want, atol=0.02)
    # metadata
    assert ShapeSpace.from_dict(space.to_dict()).param_norm_max == pytest.approx(1.0)
    assert ShapeSpace.from_dict({k: v for k, v in space.to_dict().items() if k != "param_norm_max"}).param_norm_max is None
    for bad in (-1.0, float("nan"), "wide"):
        with pytest.raises(FacesynthError, match="param_norm_max"):
            ShapeSpace.from_dict({**space.to_dict(), "param_norm_max": bad})


def test_the_heads_travel_is_bounded_by_the_avatars_own_widened():
    """ShapeSpace.shift_range: a driver moving its head less than the bound is retargeted as
    without it; one moving it far gets the head's shift (the rigid points' centroid, under the
    head motion) clipped to the avatar's range widened by SHIFT_WIDEN of its width, at least
    SHIFT_FLOOR IOD each way (closed form), the expression untouched; the graph agrees; the
    metadata round-trips and bad ranges are refused."""
    import torch

    from facesynth.errors import FacesynthError
    from facesynth.landmarks import IBUG68, inter_ocular
    from facesynth.onnx.retarget_graph import RetargetGraph
    from facesynth.retarget import SHIFT_FLOOR, SHIFT_WIDEN, Retargeter, ShapeSpace, head_shifts, rigid_points

    mean, comps, limit, _ = _residual_case()
    avatar = _faces()[1]
    driver_n = _faces()[0] * 1.4 + np.array([40.0, -25.0])
    rng_ = np.array([[-6.0, -4.0], [10.0, 2.0]])
    space = ShapeSpace(mean, comps, limit, shift_range=rng_)
    free = ShapeSpace(mean, comps, limit)
    iod = float(inter_ocular(avatar))
    lo = np.minimum(rng_[0] - SHIFT_WIDEN * (rng_[1] - rng_[0]), -SHIFT_FLOOR * iod)
    hi = np.maximum(rng_[1] + SHIFT_WIDEN * (rng_[1] - rng_[0]), SHIFT_FLOOR * iod)
    rigid = rigid_points(IBUG68)
    small = driver_n + np.array([3.0, -2.0])
    np.testing.assert_allclose(Retargeter(avatar, driver_n, space).one(small), Retargeter(avatar, driver_n, free).one(small),
                               atol=1e-9)
    far = driver_n + np.array([-900.0, 700.0])  # far left and down, in driver pixels
    got = Retargeter(avatar, driver_n, space).one(far)
    unbounded = Retargeter(avatar, driver_n, free).one(far)
    shift = head_shifts(IBUG68, avatar, got[None])[0]
    np.testing.assert_allclose(shift, [lo[0], hi[1]], atol=1e-6)
    np.testing.assert_allclose(got - got[rigid].mean(0), unbounded - unbounded[rigid].mean(0), atol=1e-9)  # a pure shift
    g = RetargetGraph(avatar, space).eval()
    frames = np.stack([small, far, driver_n + np.array([0.0, -500.0])]).astype(np.float32)
    with torch.no_grad():
        out = g(torch.from_numpy(frames), torch.from_numpy(driver_n.astype(np.float32))).numpy()
    want = Retargeter(avatar, driver_n, space)(frames)
    np.testing.assert_allclose(out, want, atol=0.02)
    back = ShapeSpace.from_dict(space.to_dict())
    np.testing.assert_array_equal(back.shift_range, rng_)
    assert ShapeSpace.from_dict(free.to_dict()).shift_range is None
    for bad in ([[1.0, 0.0], [0.0, 1.0]], [[0.0, 0.0]], [[0.0, float("nan")], [1.0, 1.0]]):
        with pytest.raises(FacesynthError, match="shift_range"):
            ShapeSpace.from_dict({**space.to_dict(), "shift_range": bad})
