"""The seam of the composite (compositing.seam_layers) against an independent erosion
(scipy), the talking-head graph's tensor form (onnx.head_parts.SeamGraph) against it (its
layers, and its whole composite in torch and in ONNX Runtime against blend_face), a face that
reaches the crop's edge fading out there instead of ending in a line, and the placed alpha
(compositing.placed_alpha) as the weight blend_face gives the face."""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
import pytest
import torch
from scipy.ndimage import minimum_filter

from facesynth.compositing import blend_face, gaussian_kernel, placed_alpha, seam_layers
from facesynth.onnx.head_parts import BLUR_BLOCK, BandedBlur, SeamGraph


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



@pytest.mark.parametrize("n, sigma", [(1, 1.0), (7, 2.5), (BLUR_BLOCK, 2.5), (BLUR_BLOCK + 1, 2.5), (150, 2.54), (300, 5.1)])
def test_the_banded_blur_is_opencvs_gaussian(n, sigma):
    """BandedBlur (the seam's Gaussian as blocks: one Gather, one MatMul) against OpenCV's
    separable filter with the same border (BORDER_REFLECT_101), axes shorter than the kernel
    and lengths that leave a partial last block included."""
    g = gaussian_kernel(sigma)
    x = np.random.default_rng(n).random((n, 37)).astype(np.float32)
    want = cv2.filter2D(x, cv2.CV_32F, g.reshape(-1, 1), borderType=cv2.BORDER_REFLECT_101)
    got = BandedBlur(g, n)(torch.from_numpy(x)[None, None])[0, 0].numpy()
    np.testing.assert_allclose(got, want, atol=2e-6)

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


class _Composite(torch.nn.Module):
    """SeamGraph as a module of its own, for export."""

    def __init__(self, seam: SeamGraph):
        super().__init__()
        self.seam = seam

    def forward(self, crop, mask, placement, frame, face):
        return self.seam(crop, mask, placement, frame, face)


@pytest.mark.parametrize("where", ["inside", "corner"])
def test_the_graphs_composite_is_blend_faces(where, tmp_path):
    """SeamGraph's composite (the face's box composed, then put into the uint8 frame by slices
    and concatenations) is blend_face's, within 2/255 (the talking head's parity; a pixel or
    none above 1): in torch, and exported and run in ONNX
    Runtime, for a face inside the frame and one cut by its top-left corner (the box on the
    frame's edge: empty slices above and left of it)."""
    import onnxruntime as ort

    mask = _masks()[0]
    h, w = mask.shape
    rng = np.random.default_rng(1)
    crop = (rng.uniform(0.2, 0.9, (3, h, w)) * mask).astype(np.float32)
    frame = rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)
    a, b = 1.2 * math.cos(0.2), 1.2 * math.sin(0.2)
    shift = (30.0, 10.0) if where == "inside" else (-14.0, -20.0)
    placement = np.array([[a, -b, shift[0]], [b, a, shift[1]]])
    want = blend_face(crop.transpose(1, 2, 0), mask, placement, frame, 3.0)
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], np.float64) @ placement.T
    args = (torch.from_numpy(crop[None]), torch.from_numpy(mask[None, None]),
            torch.from_numpy(placement[None].astype(np.float32)),
            torch.from_numpy(np.ascontiguousarray(frame.transpose(2, 0, 1)[None])),
            torch.from_numpy(corners[None].astype(np.float32)))
    graph = _Composite(SeamGraph(3.0, (120, 90), (h, w))).eval()
    with torch.no_grad():
        got = graph(*args)[0].numpy().transpose(1, 2, 0)
    diff = np.abs(got.astype(int) - want)
    assert got.dtype == np.uint8 and diff.max() <= 2 and (diff > 1).mean() < 1e-3  # float32 sums: a rounding apart
    assert (got != frame).any(1).any() and (got == frame).all(-1)[-1, -1]  # the face composed, the rest the frame
    path = tmp_path / "seam.onnx"
    names = ["crop", "mask", "placement", "frame", "face"]
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's, as facesynth.onnx.talking_head silences them
        torch.onnx.export(graph, args, str(path), input_names=names, output_names=["out"], opset_version=18,
                          dynamo=False)
    out = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        None, {k: v.numpy() for k, v in zip(names, args, strict=True)})[0][0].transpose(1, 2, 0)
    np.testing.assert_array_equal(out, got)
