"""The seam of the composite (runtime.blend.seam_layers) against an independent erosion
(scipy), the talking-head graph's tensor form (onnx.head_parts.SeamGraph) against it, a
face that reaches the crop's edge fading out there instead of ending in a line, and the
placed alpha (runtime.blend.placed_alpha) as the weight blend_face gives the face."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from scipy.ndimage import minimum_filter

from facesynth.onnx.head_parts import SeamGraph
from facesynth.runtime.blend import blend_face, gaussian_kernel, placed_alpha, seam_layers


def _masks() -> list[np.ndarray]:
    """float32 (H, W) {0, 1} crop masks: a face inside the crop, one cut by its left and bottom
    edges (a head turned far), one filling the crop."""
    h, w = 60, 52
    inside = np.zeros((h, w), np.float32)
    cv2.ellipse(inside, (26, 30), (18, 24), 0, 0, 360, 1.0, -1)
    cut = np.zeros((h, w), np.float32)
    cv2.ellipse(cut, (12, 40), (24, 26), 0, 0, 360, 1.0, -1)
    return [inside, cut, np.ones((h, w), np.float32)]


def _reference(mask: np.ndarray, feather: float) -> tuple[np.ndarray, np.ndarray]:
    """seam_layers' definition with scipy's erosion, the outside of the crop counted as 0."""
    hard = (mask > 0.5).astype(np.float32)
    r = max(1, math.ceil(feather))
    inner = minimum_filter(hard, size=2 * r + 1, mode="constant", cval=0.0)
    g = gaussian_kernel(feather / 2.0)
    alpha = cv2.sepFilter2D(inner, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT_101) * hard
    band = hard * (minimum_filter(hard, size=4 * r + 1, mode="constant", cval=0.0) == 0)
    return alpha, band


@pytest.mark.parametrize("feather", [2.0, 3.4])
def test_seam_layers_against_an_independent_erosion(feather):
    for mask in _masks():
        alpha, band = seam_layers(mask, feather)
        want_alpha, want_band = _reference(mask, feather)
        np.testing.assert_allclose(alpha, want_alpha, atol=1e-6)
        np.testing.assert_array_equal(band, want_band)


def test_a_face_cut_by_the_crop_fades_out_at_the_crop_edge():
    """Where the face reaches the crop's edge, the alpha is near 0 on the edge (the blur's tail
    reflected there: under 0.1) and rises inwards, as at the face's own outline; a line there
    (alpha 1 on the edge, the warped frame just beyond) is what a head turned far showed
    before."""
    _, cut, full = _masks()
    for mask in (cut, full):
        alpha, band = seam_layers(mask, 3.0)
        edge = np.zeros(mask.shape, bool)
        edge[0], edge[-1], edge[:, 0], edge[:, -1] = True, True, True, True
        assert alpha[edge & (mask > 0.5)].max() < 0.1
        assert band[edge & (mask > 0.5)].all()  # the colours are compared along it too
    alpha, _ = seam_layers(full, 3.0)
    assert alpha[30, 26] == pytest.approx(1.0, abs=1e-6) and np.all(np.diff(alpha[30, :26]) >= -1e-7)


@pytest.mark.parametrize("feather", [2.0, 3.4])
def test_the_graphs_seam_layers_match_numpy(feather):
    h, w = _masks()[0].shape
    graph = SeamGraph(feather, (200, 200), (h, w))
    masks = np.stack(_masks())[:, None]
    crop = np.random.default_rng(0).uniform(0, 1, (len(masks), 3, h, w)).astype(np.float32) * masks
    with torch.no_grad():
        layers, face_mean = graph.layers(torch.from_numpy(crop), torch.from_numpy(masks))
    for i, mask in enumerate(masks[:, 0]):
        alpha, band = seam_layers(mask, feather)
        np.testing.assert_allclose(layers[i, 3].numpy(), alpha, atol=1e-5)
        np.testing.assert_array_equal(layers[i, 4].numpy(), band)
        np.testing.assert_allclose(layers[i, :3].numpy(), crop[i] * alpha, atol=1e-5)
        want = (crop[i] * band).sum((1, 2)) / max(band.sum(), 1.0)
        np.testing.assert_allclose(face_mean[i].numpy(), want, atol=1e-5)


@pytest.mark.parametrize("feather", [None, 3.4])
def test_placed_alpha_is_the_weight_blend_face_gives_the_face(feather):
    """A white face on a black frame, colour matching off: blend_face's output is 255 x the
    placed alpha (rounded), for a rotated, scaled placement partly outside the frame."""
    mask = _masks()[1]
    h, w = mask.shape
    a, b = 1.7 * math.cos(0.3), 1.7 * math.sin(0.3)
    placement = np.array([[a, -b, 40.0], [b, a, -12.0]])
    size = (120, 90)
    alpha = placed_alpha(mask, placement, size, feather)
    assert alpha.shape == (90, 120) and alpha.dtype == np.float32
    assert alpha.max() == pytest.approx(1.0, abs=1e-3) and alpha.min() == 0.0
    white = np.ones((h, w, 3), np.float32)
    out = blend_face(white, mask, placement, np.zeros((90, 120, 3), np.uint8), feather, match_colour=False)
    np.testing.assert_array_equal(out[..., 0], np.clip(np.floor(alpha * 255.0 + 0.5), 0, 255))
