"""The full-frame warp (facesynth.runtime.fullframe): identity at the neutral, a rigid head
motion equals OpenCV's warpAffine on the head, the border stays still, no folds."""

import cv2
import numpy as np
import pytest

from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, thin_plate
from facesynth.runtime.fullframe import PARALLAX, FrameWarp, head_points, head_region, nose_offset
from tests._faces import face_template, smooth_image

SIZE = 320


@pytest.fixture(scope="module")
def scene():
    """A smooth (320, 320) frame with a 100-px-wide face in its middle."""
    frame = (smooth_image(SIZE, SIZE, seed=3) * 255).round().astype(np.uint8)
    face = face_template(width=100.0, cx=160.0, cy=170.0).astype(np.float64)
    return frame, face


def similarity(angle_deg: float, scale: float, shift, centre) -> np.ndarray:
    a = np.deg2rad(angle_deg)
    lin = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c = np.asarray(centre, np.float64)
    return np.concatenate([lin, (c + np.asarray(shift) - lin @ c)[:, None]], 1)


@pytest.mark.parametrize("method", ["affine", "tps"])
def test_the_neutral_is_the_identity(scene, method):
    frame, face = scene
    fw = FrameWarp(frame, face, method)
    mx, my = fw.maps(face)
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    np.testing.assert_allclose(mx, xs, atol=1e-3)
    np.testing.assert_allclose(my, ys, atol=1e-3)
    assert np.abs(fw(face).astype(int) - frame).max() <= 1
    assert fw.folds(face) == 0


def test_a_rigid_head_motion_is_opencvs_warp_on_the_head(scene):
    """Landmarks moved by one similarity: inside the head's ring every control point moves by
    it, so there the output is cv2.warpAffine's (bilinear both)."""
    frame, face = scene
    fw = FrameWarp(frame, face)
    m = similarity(6.0, 1.04, (7.0, -5.0), face.mean(0))
    out = fw(apply_affine(face, m))
    ref = cv2.warpAffine(frame, m, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # pixels of the moved face's hull (a region all of whose triangles move rigidly), eroded by 2 px
    inside = np.zeros((SIZE, SIZE), np.uint8)
    cv2.fillConvexPoly(inside, cv2.convexHull(np.round(apply_affine(face, m)).astype(np.int32)), 1)
    inside = cv2.erode(inside, np.ones((5, 5), np.uint8)).astype(bool)
    assert inside.sum() > 5000
    assert np.abs(out.astype(int) - ref)[inside].max() <= 1


def test_the_border_stays_still_away_from_the_head(scene):
    frame, face = scene
    fw = FrameWarp(frame, face)
    moved = apply_affine(face, similarity(8.0, 0.95, (10.0, 6.0), face.mean(0)))
    dst = fw.control_points(moved)
    still = fw.weights == 0
    assert still.sum() >= 4  # at least the corners
    np.testing.assert_array_equal(dst[fw.n_face:][still], fw.src[fw.n_face:][still])
    mx, my = fw.maps(moved)
    for y, x in ((0, 0), (0, SIZE - 1), (SIZE - 1, 0), (SIZE - 1, SIZE - 1)):
        assert (mx[y, x], my[y, x]) == pytest.approx((x, y), abs=1e-3)
    # a big motion: anchors near the head slide along the sides and bottom, never off them
    far = fw.control_points(apply_affine(face, similarity(15.0, 1.1, (40.0, 60.0), face.mean(0))))[fw.n_face:]
    src = fw.src[fw.n_face:]
    for axis, edge in ((0, 0.0), (0, SIZE - 1.0), (1, SIZE - 1.0)):
        on = src[:, axis] == edge
        np.testing.assert_array_equal(far[on, axis], edge)
    # the weights fall off: 1 on the head's ring, less on the outer ring, 0 at the corners
    _, w = head_points(face, (SIZE, SIZE))
    assert w.max() == 1.0 and w.min() == 0.0


def test_a_head_turn_moves_the_outline_less_than_the_face(scene):
    """Only the nose tip moves (a turn: the face's front shifts, the similarity fitted on the
    eyes, nose bridge and jaw tops stays the identity): each control point off the face moves
    by its share of minus PARALLAX times the nose's shift (closed form), the still ones not at
    all; under a similarity of the whole face the parallax term is 0 (the rigid test above)."""
    frame, face = scene
    fw = FrameWarp(frame, face)
    turned = face.copy()
    turned[30] += (9.0, -4.0)
    got = fw.control_points(turned)[fw.n_face:] - fw.src[fw.n_face:]
    want = fw.shares()[1] * -np.array([9.0, -4.0])
    np.testing.assert_allclose(fw.motion[:, 1], PARALLAX * fw.weights)
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert np.abs(got[fw.weights == 1.0]).max() > 8.0  # the head's ring takes the whole term
    assert fw.folds(turned, outside_face=True) == 0
    m = similarity(10.0, 1.05, (4.0, 3.0), face.mean(0))
    np.testing.assert_allclose(nose_offset(apply_affine(face, m)), m[:, :2] @ nose_offset(face), atol=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_head_motions_fold_nothing(scene, seed):
    """Random head motions of a talking head's range (+-12 degrees, +-8 % scale, up to a fifth
    of the face's width) with a mouth opening: every warped triangle keeps its orientation,
    and every pixel reads a map inside the neutral frame's reach."""
    frame, face = scene
    rng = np.random.default_rng(seed)
    fw = FrameWarp(frame, face)
    lm = face.copy()
    lm[[5, 6, 7, 8, 9, 10, 11] + list(range(55, 60)) + [65, 66, 67], 1] += rng.uniform(0, 15)  # the jaw drops
    m = similarity(rng.uniform(-12, 12), rng.uniform(0.92, 1.08), rng.uniform(-20, 20, 2), face.mean(0))
    moved = apply_affine(lm, m)
    assert fw.folds(moved) == 0
    mx, my = fw.maps(moved)
    assert np.isfinite(mx).all() and np.isfinite(my).all()


def test_a_chin_leaving_the_frame_pushes_the_bottom_out_and_folds_nothing():
    """A face near the frame's bottom moved down past it (turned +-10 degrees, slid sideways):
    the bottom side's anchors go a margin below the lowest landmark (closed form: the margin is
    the neutral's gap, capped at CHIN_MARGIN face units), nothing folds outside the face
    (without the push, 29 of these 40 motions fold the band between chin and anchors), and the
    talking-head graph's warp reads the same frame as numpy's."""
    import torch

    from facesynth.onnx.head_parts import FrameWarpGraph
    from facesynth.runtime.fullframe import CHIN_MARGIN, face_frame

    frame = (smooth_image(SIZE, SIZE, seed=3) * 255).round().astype(np.uint8)
    face = face_template(width=100.0, cx=160.0, cy=230.0).astype(np.float64)
    fw = FrameWarp(frame, face)
    assert fw.chin_margin == min(SIZE - 1 - face[:, 1].max(), CHIN_MARGIN * face_frame(face)[2])
    graph = FrameWarpGraph(fw).eval()
    rng = np.random.default_rng(0)
    for k in range(40):
        m = similarity(rng.uniform(-10, 10), rng.uniform(0.97, 1.05), (rng.uniform(-25, 25), rng.uniform(25, 45)),
                       face.mean(0))
        lm = apply_affine(face, m)
        dst = fw.control_points(lm)[fw.n_face:]
        want = max(SIZE - 1.0, lm[:, 1].max() + fw.chin_margin)
        np.testing.assert_allclose(dst[fw.bottom, 1], want)
        assert fw.folds(lm, outside_face=True) == 0
        if k % 8 == 0:
            with torch.no_grad():
                got = graph(torch.from_numpy(lm.astype(np.float32)[None]))[0].numpy().transpose(1, 2, 0)
            assert np.abs(got - fw(lm)).max() <= 2


def test_what_lies_beyond_the_top_edge_reads_the_frame_mirrored():
    """A head near the frame's top moved down: the top anchors follow it, so the band above
    them reads beyond the frame. It reads the frame reflected about its first row (the grid
    nodes' maps reflected, upsampled by np.interp and read by cv2.remap with no border
    mode at work), not its top row repeated (stripes: every row of the band the same), and
    the talking-head graph reads the same."""
    import torch

    from facesynth.onnx.head_parts import FrameWarpGraph

    frame = (smooth_image(SIZE, SIZE, seed=5) * 255).round().astype(np.uint8)
    face = face_template(width=100.0, cx=160.0, cy=120.0).astype(np.float64)
    fw = FrameWarp(frame, face)
    lm = apply_affine(face, similarity(3.0, 1.0, (4.0, 40.0), face.mean(0)))
    nodes = fw.node_maps(fw.control_points(lm))  # (2, Hn, Wn), unreflected
    assert nodes[1].min() < -8.0 and nodes.min() > -(SIZE - 1) and nodes.max() <= SIZE - 1 + 1e-9  # beyond the top only
    (nx, ny), pix = fw.nodes, np.arange(SIZE, dtype=np.float64)

    def up(m):  # bilinear between the nodes: along x, then along y
        m = np.stack([np.interp(pix, nx, row) for row in m])
        return np.stack([np.interp(pix, ny, col) for col in m.T], 1).astype(np.float32)

    ref = cv2.remap(frame, up(np.abs(nodes[0])), up(np.abs(nodes[1])), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    out = fw(lm)
    assert np.abs(out.astype(int) - ref).max() <= 1
    band = up(nodes[1]) < -4.0  # output pixels whose map reads 4 px or more above the frame
    assert band[:3, 100:220].all()
    rows = np.abs(np.diff(out.astype(int), axis=0)).mean(-1)[band[1:]]
    assert rows.mean() > 0.25 * np.abs(np.diff(frame[:12].astype(int), axis=0)).mean()
    with torch.no_grad():
        got = FrameWarpGraph(fw).eval()(torch.from_numpy(lm.astype(np.float32)[None]))[0].numpy().transpose(1, 2, 0)
    assert np.abs(got - out).max() <= 2


def test_a_fold_inside_the_face_is_told_apart(scene):
    """Inner lips pushed past each other fold triangles among the landmarks only: counted by
    folds(), not by folds(outside_face=True) (the composited face covers them)."""
    frame, face = scene
    fw = FrameWarp(frame, face)
    lm = face.copy()
    lm[61:64, 1] += 12.0  # the upper inner lip below the lower one
    lm[65:68, 1] -= 12.0
    assert fw.folds(lm) > 0
    assert fw.folds(lm, outside_face=True) == 0


def test_thin_plate_interpolates_and_reproduces_affine_maps(rng):
    ctrl = rng.uniform(0, 100, (20, 2))
    m = np.array([[1.1, 0.2, 3.0], [-0.1, 0.9, -2.0]])
    at = rng.uniform(0, 100, (50, 2))
    np.testing.assert_allclose(thin_plate(ctrl, apply_affine(ctrl, m), at), apply_affine(at, m), atol=1e-6)
    vals = rng.normal(0, 5, (20, 2))
    np.testing.assert_allclose(thin_plate(ctrl, vals, ctrl), vals, atol=5e-3)  # the small regularisation


def test_head_region_takes_in_hair_and_neck(scene):
    _, face = scene
    region = head_region(face, (SIZE, SIZE))
    hull = np.zeros((SIZE, SIZE), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(face).astype(np.int32)), 1)
    assert region[hull > 0].all()
    assert region.sum() > 2 * hull.sum()
    top = int(np.floor(face[:, 1].min()))
    assert region[: top - 20, int(face[:, 0].mean())].any()  # above the brows: hair


def test_bad_inputs(scene):
    frame, face = scene
    with pytest.raises(FacesynthError, match="method"):
        FrameWarp(frame, face, "mls")
    with pytest.raises(FacesynthError, match="uint8"):
        FrameWarp(frame.astype(np.float32), face)
    with pytest.raises(FacesynthError, match="not finite"):
        FrameWarp(frame, np.full((68, 2), np.nan))


def test_ssim_matches_kornia(rng):
    """facesynth.metrics.ssim against kornia's (same window; the interior, where the border
    padding plays no part), and its bounds."""
    import torch
    from kornia.metrics import ssim as kornia_ssim

    from facesynth.metrics import ssim

    a = (smooth_image(64, 80, seed=1) * 255).astype(np.float64)
    b = np.clip(a + rng.normal(0, 12, a.shape), 0, 255)
    ref = kornia_ssim(*(torch.from_numpy(x.transpose(2, 0, 1)[None] / 255.0) for x in (a, b)), 11)[0].mean(0).numpy()
    inner = np.zeros((64, 80), bool)
    inner[6:-6, 6:-6] = True
    assert ssim(a, b, inner) == pytest.approx(float(ref[inner].mean()), abs=1e-4)
    assert ssim(a, a) == pytest.approx(1.0)
    assert ssim(a, b) < 0.9
    with pytest.raises(FacesynthError, match="ssim"):
        ssim(a, b[:10])


def test_a_478_point_avatar_warps_on_its_ibug68_view(scene, shared_mesh):
    """A mediapipe478 neutral and frame landmarks warp as their iBUG-68 views do (the full-frame
    warp's control points are the 68 points whatever the scheme)."""
    from facesynth.landmarks import MEDIAPIPE478
    from tests._dense import template478, to478

    frame, face = scene
    t = template478(shared_mesh / "mediapipe_canonical_468_arrays.npz")
    moved = apply_affine(face, similarity(-5.0, 1.03, (-6.0, 4.0), face.mean(0)))
    n478, m478 = to478(np.stack([face, moved]), t)
    dense, sparse = FrameWarp(frame, n478), FrameWarp(frame, MEDIAPIPE478.to_ibug68(n478))
    for a, b in zip(dense.maps(m478), sparse.maps(MEDIAPIPE478.to_ibug68(m478)), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-4)
    assert np.abs(dense(n478).astype(int) - frame).max() <= 1
