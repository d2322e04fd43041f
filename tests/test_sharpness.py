"""Sharpness (facesynth.eval.sharpness): the Sobel energy ratio against closed forms."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facesynth.eval.sharpness import gradient_energy, median_table, sharpness


def test_ramp_energy_is_the_closed_form():
    """On I = a x + b y the 3x3 Sobel is 8a and 8b inside the image: energy 64 (a^2 + b^2) per channel."""
    ys, xs = np.mgrid[0:40, 0:50].astype(np.float64)
    img = np.stack([0.7 * xs + 0.2 * ys, 1.5 * xs - 0.4 * ys, 0.0 * xs + 0.3 * ys], -1)
    e = gradient_energy(img)[2:-2, 2:-2]
    assert e == pytest.approx(np.full_like(e, 64 * (0.7**2 + 0.2**2 + 1.5**2 + 0.4**2 + 0.3**2)), rel=1e-5)
    inner = np.zeros((40, 50), bool)
    inner[2:-2, 2:-2] = True
    # a ramp of half the slopes keeps a quarter of the energy
    assert sharpness(img / 2, img, {"r": inner})["r"] == pytest.approx(0.25, rel=1e-6)


def test_image_scores_one_and_a_blurred_copy_less():
    rng = np.random.default_rng(0)
    real = np.clip(cv2.GaussianBlur(rng.uniform(0, 255, (64, 64, 3)).astype(np.float32), (0, 0), 1.0), 0, 255).astype(np.uint8)
    mask = np.zeros((64, 64), bool)
    mask[8:56, 8:56] = True
    blurred = cv2.GaussianBlur(real, (0, 0), 2.0)
    s = sharpness(real, real, {"m": mask, "none": np.zeros_like(mask)})
    assert s["m"] == 1.0 and np.isnan(s["none"])
    b = sharpness(blurred, real, {"m": mask})["m"]
    assert 0 < b < 0.5
    # against a direct computation with OpenCV's Sobel on each channel
    def energy(im):
        f = im.astype(np.float64)
        return sum((cv2.Sobel(f[..., c], cv2.CV_64F, 1, 0) ** 2 + cv2.Sobel(f[..., c], cv2.CV_64F, 0, 1) ** 2)[mask].sum()
                   for c in range(3))
    assert b == pytest.approx(energy(blurred) / energy(real), rel=1e-5)


def test_median_table_skips_nan_frames():
    t = median_table({"sadm": {"whole": [0.5, np.nan, 0.7, 0.6]}, "oracle": {"whole": [np.nan]}})
    assert t["whole"]["sadm"] == pytest.approx(0.6) and np.isnan(t["whole"]["oracle"])
