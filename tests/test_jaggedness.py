"""The talking head's outline measure (facesynth.eval.jaggedness): a stair-stepped edge
against a smooth one drawn with integer arithmetic, scipy's Sobel as a second reference, the
exact warp against OpenCV's per-triangle affine maps, and the warp's grid step seen by it."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from facesynth.errors import FacesynthError
from facesynth.eval.jaggedness import edge_staircase, exact_warp, outline_figures, silhouette_band
from facesynth.geometry import apply_affine
from facesynth.runtime.fullframe import FrameWarp
from tests._faces import face_template, smooth_image

SIZE = 320
SUB = 8  # supersamples per pixel side


def edge_image(step: int, size: int = 96) -> np.ndarray:
    """uint8 (size, size): white below the line y = (x0 + 40) / 2 + 20 scaled by 2 (slope 1/2),
    where x0 is the supersample's x (step 1: the smooth edge) or that x floored to a multiple
    of ``step`` (a staircase of ``step`` px treads), the coverage counted on SUB x SUB
    supersamples in int64 (exact, no rounding of the line)."""
    s = np.arange(size * SUB, dtype=np.int64)  # supersample centres at (s + 1/2) / SUB px, in units of 1/(2 SUB)
    xs, ys = 2 * s[None, :] + 1, 2 * s[:, None] + 1
    x0 = xs if step == 1 else (xs // (2 * SUB * step)) * (2 * SUB * step)
    below = 2 * ys > x0 + 2 * (2 * SUB * 20)  # y > x0 / 2 + 20, all in units of 1/(2 SUB)
    count = below.reshape(size, SUB, size, SUB).sum((1, 3))
    return (count * 255 // (SUB * SUB)).astype(np.uint8)


def test_a_staircase_scores_by_its_steps_and_a_smooth_edge_nothing():
    smooth = edge_image(1)
    assert edge_staircase(smooth, smooth) == 0.0
    scores = [edge_staircase(edge_image(k), smooth) for k in (2, 4, 8)]
    assert 0 < scores[0] < scores[1] < scores[2]
    assert scores[2] > 0.3  # 8 px treads: a third of the edge's energy again in risers and treads
    # the same ratio with scipy's Sobel (an independent implementation) on the same pixels
    def energy(img):
        img = img.astype(np.float64)
        return (ndimage.sobel(img, 1, mode="reflect") ** 2 + ndimage.sobel(img, 0, mode="reflect") ** 2)[2:-2, 2:-2].sum()

    inner = np.zeros(smooth.shape, bool)
    inner[2:-2, 2:-2] = True
    stair = edge_image(8)
    want = energy(stair.astype(np.float64) - smooth) / energy(smooth)
    assert edge_staircase(stair, smooth, inner) == pytest.approx(want, rel=1e-5)


def test_edge_staircase_refuses_images_of_two_shapes():
    with pytest.raises(ValueError, match="shapes"):
        edge_staircase(np.zeros((4, 4)), np.zeros((4, 5)))


@pytest.fixture(scope="module")
def head():
    """A smooth (320, 320) frame with a dark head and neck (the jaw's outline a sharp edge),
    its face's landmarks, and the landmarks of a head turn: the face moved and turned, the
    nose tip ahead of it (the parallax the neck points follow only in part)."""
    frame = (smooth_image(SIZE, SIZE, seed=3) * 255).round().astype(np.uint8)
    face = face_template(width=100.0, cx=160.0, cy=150.0).astype(np.float64)
    neck = np.array([[face[16, 0] - 10, SIZE - 1], [face[0, 0] + 10, SIZE - 1]])
    cv2.fillPoly(frame, [np.round(np.concatenate([face[:17], neck]) * 16).astype(np.int32)], (40, 30, 25), cv2.LINE_AA, 4)
    a = np.deg2rad(8.0)
    rot = 1.02 * np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0]])
    c = face.mean(0)
    rot[:, 2] = c + np.array([18.0, -6.0]) - rot[:, :2] @ c
    turned = apply_affine(face, rot)
    turned[27:36, 0] += 6.0  # the nose turns ahead of the skull
    turned[:17, 0] += np.linspace(4.0, -4.0, 17)  # the jaw's near side narrows
    return frame, face, turned


def test_the_exact_warp_is_opencvs_affine_map_per_triangle(head):
    """grid_step=1: every pixel well inside an unfolded warped triangle reads the neutral
    frame where that triangle's own affine map (cv2.getAffineTransform) sends it."""
    frame, face, turned = head
    fw = exact_warp(FrameWarp(frame, face))
    mx, my = fw.maps(turned)
    dst = fw.control_points(turned)
    checked = 0
    for tri in fw.triangles:
        d, s = dst[tri].astype(np.float32), fw.src[tri].astype(np.float32)
        def cross(p):
            (ax, ay), (bx, by) = p[1] - p[0], p[2] - p[0]
            return float(ax) * float(by) - float(ay) * float(bx)

        area = cross(d) * cross(s)
        if area <= 0:
            continue  # folded
        m = cv2.getAffineTransform(d, s)
        inside = np.zeros((SIZE, SIZE), np.uint8)
        cv2.fillConvexPoly(inside, np.round(d * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        ys, xs = np.nonzero(cv2.erode(inside, np.ones((3, 3), np.uint8)))
        if not len(xs):
            continue
        want = apply_affine(np.stack([xs, ys], 1).astype(np.float64), m)
        np.testing.assert_allclose(np.stack([mx[ys, xs], my[ys, xs]], 1), want, atol=2e-3)
        checked += len(xs)
    assert checked > 0.8 * SIZE * SIZE


def test_the_grid_step_is_seen_along_the_outline(head):
    """The coarser the warp's grid, the further its map from the exact one along the jaw and
    the more staircase energy it draws there; the exact warp draws none."""
    frame, face, turned = head
    exact = exact_warp(FrameWarp(frame, face))
    got = {k: outline_figures(FrameWarp(frame, face, grid_step=k), turned, exact) for k in (1, 4, 8)}
    assert got[1] == {"map_px_p99": 0.0, "map_px_max": 0.0, "staircase": 0.0}
    assert 0 < got[4]["map_px_p99"] < got[8]["map_px_p99"]
    assert 0 < got[4]["staircase"] < got[8]["staircase"]


def test_the_silhouette_band_holds_the_jaw_not_the_face(head):
    _, face, _ = head
    band = silhouette_band(face, (SIZE, SIZE))
    jaw = np.round(face[:17]).astype(int)
    assert band[jaw[:, 1], jaw[:, 0]].all()
    nose = np.round(face[30]).astype(int)
    assert not band[nose[1], nose[0]]
    assert band[:, :40].sum() == 0  # the background beside the head is not in it


@pytest.mark.parametrize("step", [0, 2.5, True, "4"])
def test_a_bad_grid_step_is_one_error(head, step):
    frame, face, _ = head
    with pytest.raises(FacesynthError, match="grid_step"):
        FrameWarp(frame, face, grid_step=step)
