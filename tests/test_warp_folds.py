"""The render warp leaves no hole for folded landmark sets (swapped points, a jaw pushed
across the cheek), in torch and in ONNX Runtime, with parity <= 1e-4 (issue 13), nor where
a triangle folded on the mean shape unfolds (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _onnx_models import exported, synthetic_synthesizer

from facesynth.geometry import apply_affine, similarity_fit
from facesynth.landmarks import folded_triangles
from facesynth.model.reference import ReferenceFrame, barycentric
from facesynth.model.warp import ToTarget, candidate_spans
from facesynth.runtime import Renderer


def _folded_sets(syn) -> np.ndarray:
    """(3, 68, 2) frame landmarks whose canvas shapes fold triangles of the mesh."""
    ref = syn.ref_points.numpy().astype(np.float64)
    frame = ref * 2.0 + [40.0, 30.0]  # frame = canvas scaled and moved
    swapped = frame.copy()
    swapped[[61, 67]] = swapped[[67, 61]]  # upper and lower inner lip swapped
    swapped[[37, 41]] = swapped[[41, 37]]  # an eyelid turned inside out
    jaw = frame.copy()
    jaw[[3, 4]] += 0.6 * (frame[[31, 48]] - frame[[3, 4]])  # jaw pushed across the cheek
    brow = frame.copy()
    brow[[19, 20]] = frame[[37, 38]] + [0.0, 6.0]  # brow pulled below the eyelid
    return np.stack([swapped, jaw, brow]).astype(np.float32)


def _canvas(syn, lm):
    m = similarity_fit(lm.astype(np.float64), syn.ref_points.numpy().astype(np.float64)[None])
    return apply_affine(lm.astype(np.float64), m[0])


def _covered(points, triangles, size, margin=0.02):
    """bool (H, W): pixel centres strictly inside at least one triangle (brute force)."""
    h, w = size
    ys, xs = np.mgrid[0:h, 0:w]
    pix = np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64)
    b = barycentric(pix, points[triangles])
    return (b > margin).all(-1).any(1).reshape(h, w)


def _flipped(points, triangles):
    p = points[triangles]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return int((e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0).sum())


@pytest.fixture(scope="module")
def folded():
    syn = synthetic_synthesizer("linear")
    return syn, _folded_sets(syn)


def test_folds_leave_no_hole_in_torch(folded):
    syn, lm = folded
    tri = syn.warp.tri.numpy()
    with torch.no_grad():
        crop, mask, _ = syn(torch.from_numpy(lm))
        canvas = torch.from_numpy(np.stack([_canvas(syn, x) for x in lm]).astype(np.float32))
        assert not syn.warp.clipped_triangles(canvas).any(), "test shapes must stay within the warp spans"
    for i, x in enumerate(lm):
        pts = _canvas(syn, x)
        assert _flipped(pts, tri) >= 1, f"set {i} folds no triangle"
        inside = _covered(pts, tri, mask.shape[-2:])
        m = mask[i, 0].numpy() > 0.5
        holes = inside & ~m
        assert holes.sum() == 0, f"set {i}: {int(holes.sum())} uncovered pixels inside the face"
        # nothing outside the union of the triangles (1 px of rounding at the outline)
        grown = _covered(pts, tri, mask.shape[-2:], margin=-0.08)
        assert (m & ~grown).sum() == 0
        # the face is textured where it is covered (no black holes in the crop)
        assert (crop[i].numpy().max(0)[inside] > 0.02).mean() > 0.99


def test_folds_parity_in_onnx_runtime(folded, tmp_path):
    syn, lm = folded
    r = Renderer(exported("linear", tmp_path))
    crop, mask, _ = r.render(lm, copy=True)
    with torch.no_grad():
        t_crop, t_mask, _ = (t.numpy() for t in syn(torch.from_numpy(lm)))
    assert (mask != t_mask).mean() < 1e-4
    both = mask * t_mask
    assert np.abs((crop - t_crop) * both).max() <= 1e-4
    tri = syn.warp.tri.numpy()
    for i, x in enumerate(lm):
        inside = _covered(_canvas(syn, x), tri, mask.shape[-2:])
        assert (inside & (mask[i, 0] < 0.5)).sum() == 0


def test_a_triangle_folded_on_the_mean_still_covers_a_target_that_unfolds_it():
    """A square split at a centre vertex that the mean pushes out past one side: that
    triangle is folded on the mean (it overlaps the other three). The reference keeps it
    (turned counter-clockwise, last), so a target with the centre back inside is covered
    everywhere, including the quarter that only the folded triangle covers there
    (dropping it, as before stop 21, left that quarter as a hole)."""
    fixed = np.array([[1, 0, 4], [2, 1, 4], [3, 2, 4], [0, 3, 4]])
    corners = np.array([[0.0, 40.0], [40.0, 40.0], [40.0, 0.0], [0.0, 0.0]])  # image axes, y down
    mean = np.concatenate([corners, [[20.0, 52.0]]])  # centre pushed below side 0-1
    assert folded_triangles(mean, fixed).tolist() == [True, False, False, False]
    ref = ReferenceFrame.from_mean_shape(mean, width=64, margin=0.1, triangles=fixed)
    assert ref.n_triangles == 4 and {frozenset(t) for t in ref.triangles[3:].tolist()} == {frozenset(fixed[0])}
    assert not folded_triangles(ref.points, ref.triangles).any()
    target = ref.points.astype(np.float64).copy()
    target[4] = target[:4].mean(0)  # the centre back inside: every triangle unfolded
    assert not folded_triangles(target, fixed).any()
    inside = _covered(target, fixed, ref.size)
    assert (inside & ~_covered(target, fixed[1:], ref.size)).sum() > 100  # the quarter only the folded one covers
    warp = ToTarget(ref, candidate_spans(ref, target[None]))
    tex = torch.ones(1, 3, warp.n_mask)
    with torch.no_grad():
        img, mask = warp(tex, torch.from_numpy(target[None].astype(np.float32)))
    m = mask[0, 0].numpy() > 0.5
    assert (inside & ~m).sum() == 0
    assert (img[0].numpy().min(0)[inside] > 0.99).all()  # textured there, not black
