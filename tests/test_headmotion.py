"""The full-frame warp's motion learned from the avatar's video (facesynth.onnx.headmotion):
a synthetic video made with known coefficients gives them back (exactly from the true
displacements, closely from DIS flow), the ridge leads to the prior, bad frames and metadata
are refused, and the talking-head graph reads the frame numpy reads with a learned motion
that leaves border anchors still on grid nodes."""

import cv2
import numpy as np
import pytest

from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine
from facesynth.onnx.headmotion import fit_frame_motion, fit_motion, ring_clearance
from facesynth.runtime.fullframe import FrameWarp
from facesynth.runtime.reenact import Avatar
from tests._faces import face_template, smooth_image
from tests.test_fullframe import similarity

SIZE = 320


@pytest.fixture(scope="module")
def video():
    """A textured frame with a face (optical flow needs texture), the true coefficients
    (every point off the head's ring and the still guard ring takes its own (a, b), below the
    prior) and 24 frames warped with them: head motions of +-6 degrees, +-4 % scale, +-8 px,
    and the nose tip moved by up to 10 px as by a turn."""
    grain = np.random.default_rng(1).normal(0.0, 40.0, (SIZE, SIZE, 3))
    grain = cv2.GaussianBlur(grain, (0, 0), 1.5)
    frame = np.clip(smooth_image(SIZE, SIZE, seed=5) * 255 + grain, 0, 255).round().astype(np.uint8)
    face = face_template(width=100.0, cx=160.0, cy=150.0).astype(np.float64)
    fw = FrameWarp(frame, face)
    rng = np.random.default_rng(0)
    truth = fw.prior()
    free = ~fw.guard & fw.free.any(1) & ~fw.on_ring
    truth[free] *= rng.uniform(0.1, 0.9, (free.sum(), 2))  # the fit lets them follow less than the prior, never more
    truth[fw.on_ring, 1] = 0.6
    gen = FrameWarp(frame, face, motion=truth)
    landmarks, frames = [], []
    for _ in range(24):
        m = similarity(rng.uniform(-6, 6), rng.uniform(0.96, 1.04), rng.uniform(-8, 8, 2), face.mean(0))
        lm = apply_affine(face, m)
        lm[30] += rng.uniform(-10, 10, 2)  # the nose tip: a turn's parallax
        landmarks.append(lm)
        frames.append(gen(lm))
    return fw, truth, np.stack(landmarks), frames


def test_the_fit_is_least_squares_on_the_points_displacements(video, monkeypatch):
    """With the flow replaced by each point's true displacement, the coefficients come back
    exactly (but the ring's a, kept at 1, and the still guard ring's prior)."""
    from facesynth.onnx import headmotion

    fw, truth, landmarks, frames = video
    gen = FrameWarp(fw.frame, fw.neutral68, motion=truth)
    moves = iter([(gen.control_points(lm) - gen.src)[gen.n_face:] for lm in landmarks])
    monkeypatch.setattr(headmotion, "flow_at", lambda grey0, grey, points: next(moves))
    coef, info = fit_motion(fw, frames, landmarks, lam=0.0)
    assert info["frames"] == 24 and info["points_fitted"] == int((~fw.guard & fw.free.any(1)).sum())
    np.testing.assert_allclose(coef, truth, atol=1e-9)
    np.testing.assert_allclose(coef[fw.on_ring, 0], 1.0, atol=1e-6)  # the ring moves in full
    # surroundings that followed the head further than the prior (a camera following the head)
    # are held at the prior
    ahead = FrameWarp(fw.frame, fw.neutral68, motion=np.minimum(1.5 * fw.prior(), 1.2))
    moves = iter([(ahead.control_points(lm) - ahead.src)[ahead.n_face:] for lm in landmarks])
    coef, _ = fit_motion(fw, frames, landmarks, lam=0.0)
    off = ~fw.guard & fw.free.any(1) & ~fw.on_ring
    np.testing.assert_allclose(coef[off], fw.prior()[off], atol=1e-9)


def test_dis_flow_reads_the_video(video):
    """The real optical flow: DIS reads about 5 % short and smooths across the mesh's kinks
    (the neck under the jaw), so the coefficients of the points the frame sees come back
    within 0.05 in the median and 0.4 at worst."""
    fw, truth, landmarks, frames = video
    coef, _ = fit_motion(fw, frames, landmarks, lam=0.0)
    inside = (fw.src[fw.n_face:] >= 2).all(1) & (fw.src[fw.n_face:] <= SIZE - 3).all(1)
    assert inside.sum() >= 20
    err = np.abs(coef[inside] - truth[inside])
    assert np.median(err) <= 0.05 and err.max() <= 0.4
    np.testing.assert_array_equal(coef[fw.guard], fw.prior()[fw.guard])  # the guard ring stays still


def test_the_ridge_leads_to_the_prior_and_no_frames_keep_it(video):
    fw, _, landmarks, frames = video
    strong, _ = fit_motion(fw, frames, landmarks, lam=1e9)
    np.testing.assert_allclose(strong, fw.prior(), atol=1e-6)
    none, info = fit_motion(fw, [], landmarks[:0])
    assert info["frames"] == 0
    np.testing.assert_array_equal(none, np.clip(fw.prior(), 0.0, 1.2))


def test_the_chosen_warp_renders_as_one_built_with_its_motion(video):
    """fit_frame_motion's warp (a ring size's candidate given its fitted motion) against a warp
    constructed with that motion and ring size: the same control points and frame."""
    fw, _, landmarks, frames = video
    got, info = fit_frame_motion(fw.frame, fw.neutral68, frames[:12], landmarks[:12], frames[12:16], landmarks[12:16])
    built = FrameWarp(fw.frame, fw.neutral68, motion=got.motion, ring_scale=info["ring_scale"])
    assert got.ring_scale == info["ring_scale"]
    for lm in landmarks[16:19]:
        np.testing.assert_array_equal(got.control_points(lm), built.control_points(lm))
        np.testing.assert_array_equal(got(lm), built(lm))


def test_bad_frames_and_metadata_are_refused(video):
    fw, _, landmarks, frames = video
    with pytest.raises(FacesynthError, match="frame of shape"):
        fit_motion(fw, [frames[0][:100]], landmarks[:1])
    with pytest.raises(FacesynthError, match="frame_motion"):
        Avatar({"frame_motion": {"coefficients": [[0.5, 0.5, 0.5]]}}, "m.onnx")
    with pytest.raises(FacesynthError, match="frame_motion"):
        Avatar({"frame_motion": [1, 2]}, "m.onnx")
    with pytest.raises(FacesynthError, match="frame_motion"):
        FrameWarp(fw.frame, fw.neutral68, motion=np.zeros((3, 2)))
    with pytest.raises(FacesynthError, match="ring_scale"):
        Avatar({"frame_motion": {"coefficients": [[0.5, 0.5]], "ring_scale": -1}}, "m.onnx")
    with pytest.raises(FacesynthError, match="ring_scale"):
        Avatar({"frame_motion": {"coefficients": [[0.5, 0.5]], "ring_scale": "wide"}}, "m.onnx")
    with pytest.raises(FacesynthError, match="ring_scale"):
        FrameWarp(fw.frame, fw.neutral68, ring_scale=float("nan"))


def test_ring_clearance_agrees_with_matplotlib_on_which_rings_enter_the_face(video):
    """A ring whose clearance is negative has a point inside the face's landmark hull, by
    matplotlib's point-in-polygon test; one whose clearance is positive has none; and the
    clearance grows with the ring."""
    from matplotlib.path import Path as MplPath
    from scipy.spatial import ConvexHull

    from facesynth.runtime.fullframe import HEAD_RING_DEG, ellipse_points, face_frame

    face = video[0].neutral68
    o, axes, unit = face_frame(face)
    xy = (face - o) @ axes.T / unit
    hull = MplPath(xy[ConvexHull(xy).vertices])
    scales = np.linspace(0.3, 1.5, 25)
    clear = np.array([ring_clearance(face, s) for s in scales])
    assert (np.diff(clear) > 0).all() and clear[0] < 0 < clear[-1]
    for s, c in zip(scales, clear, strict=True):
        inside = hull.contains_points(ellipse_points(HEAD_RING_DEG, s))
        assert inside.any() == (c < 0), (s, c)


def test_the_ring_size_that_renders_the_video_is_chosen(video, monkeypatch):
    """Frames made by a warp whose ring is 0.9 times the default: of 0.9, 1.2 and 1.5, the fit
    keeps 0.9 (it renders the held-apart frames best); a ring that enters the face is not
    tried, and a size whose warp folds on more validation frames than another's is left out."""
    fw = video[0]
    gen = FrameWarp(fw.frame, fw.neutral68, ring_scale=0.9)
    rng = np.random.default_rng(2)
    landmarks = []
    for _ in range(24):  # gentler turns than the fixture's, which fold a ring this small
        lm = apply_affine(fw.neutral68, similarity(rng.uniform(-6, 6), rng.uniform(0.96, 1.04), rng.uniform(-8, 8, 2),
                                                   fw.neutral68.mean(0)))
        lm[30] += rng.uniform(-4, 4, 2)
        landmarks.append(lm)
    assert not any(gen.folds(lm, outside_face=True) for lm in landmarks)
    frames = [gen(lm) for lm in landmarks]
    args = (fw.frame, fw.neutral68, frames[:16], landmarks[:16], frames[16:], landmarks[16:])
    warp, info = fit_frame_motion(*args, scales=(0.3, 0.9, 1.2, 1.5))
    assert info["ring_scale"] == warp.ring_scale == 0.9 and info["validation_frames"] == 8
    scores = info["ring_scores"]
    assert scores["0.3"] is None and scores["0.9"] > max(scores["1.2"], scores["1.5"])
    assert warp.motion.shape == (len(warp.src) - warp.n_face, 2)
    monkeypatch.setattr(FrameWarp, "folds", lambda self, lm, outside_face=False: int(self.ring_scale == 0.9))
    _, info = fit_frame_motion(*args, scales=(0.9, 1.2, 1.5))
    assert info["ring_scores"]["0.9"] is None and info["ring_scale"] in (1.2, 1.5)



def test_the_graph_reads_the_same_frame_as_numpy_off_by_float_noise(shared_clip_dir):
    """vrt_face1 (700 x 700) with its learned motion: anchors of the frame's top edge that the
    fit leaves (nearly) still sit on nodes of the warp's grid, where a millionth of a pixel
    decides which triangle holds the node. The graph, fed each third frame's landmarks with
    float32-sized noise (three draws), reads the frame numpy reads, within 2/255 (before the
    border anchors were pushed out for locating the nodes, one draw read a node's map as
    (0, 0): 88/255 along the top edge, as the talking-head graph did on one frame)."""
    import torch

    from facesynth.data import load_sequence, temporal_split
    from facesynth.neutral import select_neutral
    from facesynth.onnx.head_parts import FrameWarpGraph

    seq = load_sequence(shared_clip_dir("vrt_face1"))
    train, _ = temporal_split(len(seq))
    lm = np.asarray(seq.landmarks, np.float64)
    n = int(train[select_neutral(lm[train])[0]])
    probe = FrameWarp(np.asarray(seq.frame(n)), lm[n])
    rows = train[np.linspace(0, len(train) - 1, 60).round().astype(int)]
    coef, _ = fit_motion(probe, seq.iter_frames(rows), lm[rows])
    fw = FrameWarp(probe.frame, lm[n], motion=coef)
    graph = FrameWarpGraph(fw).eval()
    rng = np.random.default_rng(0)
    worst = 0.0
    for i in range(0, len(lm), 3):
        want = fw(lm[i])
        for _ in range(3):
            noisy = (lm[i] + rng.normal(0.0, 3e-5, lm[i].shape)).astype(np.float32)
            with torch.no_grad():
                got = graph(torch.from_numpy(noisy[None]))[0].numpy().transpose(1, 2, 0)
            worst = max(worst, float(np.abs(got - want).max()))
    assert worst <= 2
