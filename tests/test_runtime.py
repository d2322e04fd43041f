"""The torch-free runtime: Renderer (validation, batching, buffers), compositing, the One
Euro filter against the paper's reference form, and the ``facesynth app`` command."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch
from _onnx_models import driving_landmarks, exported, real_linear_synthesizer, synthetic_synthesizer

from facesynth.errors import FacesynthError
from facesynth.runtime import OneEuroFilter, Renderer, composite, smooth_landmarks
from facesynth.runtime.app import default_size, parse_size
from facesynth.runtime.pipeline import latency_summary, render_frames

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return exported("linear", tmp_path_factory.mktemp("rt"))


def test_runtime_never_imports_torch():
    code = ("import sys, facesynth.runtime, facesynth.runtime.app, facesynth.onnx.cli; "
            "from facesynth.runtime import Renderer; assert 'torch' not in sys.modules, 'torch imported'")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr[-1500:]


def test_render_matches_torch_and_reuses_buffers(model_path):
    syn = synthetic_synthesizer("linear")
    r = Renderer(model_path, threads=1)
    lm = driving_landmarks(seed=7, n=4)
    crops, masks, places = r.render(lm, copy=True)
    with torch.no_grad():
        t = [v.numpy() for v in syn(torch.from_numpy(lm))]
    assert np.abs((crops - t[0]) * masks * t[1]).max() <= 1e-4 and (masks != t[1]).mean() < 1e-4
    np.testing.assert_allclose(places, t[2], rtol=1e-5, atol=1e-3)
    one = r.render(lm[2])  # (68, 2) -> batch of one, written into the batch-1 buffers
    np.testing.assert_allclose(one[0][0], crops[2], atol=1e-5)  # batch-1 GEMV vs batched GEMM rounding
    again = r.render(lm[3:4])
    assert again[0] is one[0]  # preallocated outputs are reused
    assert r.crop_size == tuple(syn.warp.canvas) and r.metadata["regressor"] == "linear"


def test_render_frame_equals_torch_composite(model_path):
    from facesynth.compositing import composite as torch_side_composite

    syn = synthetic_synthesizer("linear")
    lm = driving_landmarks(seed=8, n=1)
    bg = np.random.default_rng(0).integers(0, 255, (200, 190, 3), dtype=np.uint8)
    frame = Renderer(model_path).render_frame(lm[0], bg)
    with torch.no_grad():
        crop, mask, place = syn(torch.from_numpy(lm))
    ref = torch_side_composite(crop[0].permute(1, 2, 0).numpy(), mask[0, 0].numpy(), place[0].numpy().astype(np.float64), bg)
    assert frame.shape == bg.shape and frame.dtype == np.uint8
    assert np.abs(frame.astype(int) - ref.astype(int)).max() <= 1
    assert (frame != bg).any()


def test_composite_is_the_synthesis_composite():
    from facesynth.compositing import composite as torch_side_composite

    rng = np.random.default_rng(1)
    crop = rng.random((40, 36, 3), dtype=np.float32)
    mask = np.zeros((40, 36), np.float32)
    mask[5:35, 6:30] = 1
    place = np.array([[1.2, 0.1, 30.0], [-0.1, 1.2, 20.0]])
    bg = rng.integers(0, 255, (100, 90, 3), dtype=np.uint8)
    for feather in (0.0, 2.0, 3.5):
        np.testing.assert_array_equal(composite(crop, mask, place, bg, feather), torch_side_composite(crop, mask, place, bg, feather))


@pytest.mark.parametrize("bad, match", [
    (np.zeros((2, 68, 3), np.float32), r"shape \(B, 68, 2\)"),
    (np.zeros((2, 67, 2), np.float32), r"shape \(B, 68, 2\)"),
    (np.zeros((0, 68, 2), np.float32), r"shape \(B, 68, 2\)"),
    (np.array([["a"] * 2] * 68), "dtype"),
    (np.full((3, 68, 2), np.nan, np.float32), r"NaN .* rows \[0, 1, 2\]"),
    (np.ones((2, 68, 2), np.float32), r"degenerate .* rows \[0, 1\]"),
])
def test_bad_landmarks_are_clear_errors(model_path, bad, match):
    with pytest.raises(FacesynthError, match=match):
        Renderer(model_path).render(bad)


def test_bad_models_are_clear_errors(model_path, tmp_path):
    with pytest.raises(FacesynthError, match="not found"):
        Renderer(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(FacesynthError, match="not a loadable ONNX model"):
        Renderer(tmp_path / "junk.onnx")
    m = onnx.load(str(model_path))
    for scheme, match in (("mediapipe478", r"metadata 'n_landmarks' is 68, but scheme 'mediapipe478' has 478 points"),
                          ("dlib5", r"landmark scheme 'dlib5'; this runtime knows ibug68, .*mediapipe478")):
        for prop in m.metadata_props:
            if prop.key == "landmark_scheme":
                prop.value = scheme
        onnx.save(m, str(tmp_path / "scheme.onnx"))
        with pytest.raises(FacesynthError, match=match):
            Renderer(tmp_path / "scheme.onnx")
    del m.metadata_props[:]
    onnx.save(m, str(tmp_path / "plain.onnx"))
    with pytest.raises(FacesynthError, match="not a facesynth synthesis model"):
        Renderer(tmp_path / "plain.onnx")
    with pytest.raises(FacesynthError, match="threads"):
        Renderer(model_path, threads=0)


def _one_euro_reference(xs, rate, min_cutoff, beta, d_cutoff):
    """Scalar transcription of the paper's pseudocode (Casiez et al. 2012, Algorithm 1)."""
    def alpha(cutoff):
        te = 1.0 / rate
        tau = 1.0 / (2 * np.pi * cutoff)
        return 1.0 / (1.0 + tau / te)

    out, x_hat, dx_hat = [], None, 0.0
    for x in xs:
        if x_hat is None:
            x_hat = x
        else:
            dx = (x - x_hat) * rate
            dx_hat = alpha(d_cutoff) * dx + (1 - alpha(d_cutoff)) * dx_hat
            a = alpha(min_cutoff + beta * abs(dx_hat))
            x_hat = a * x + (1 - a) * x_hat
        out.append(x_hat)
    return np.array(out)


def test_one_euro_matches_the_paper_and_smooths(rng):
    t = np.arange(200) / 30.0
    clean = 100 + 20 * np.sin(2 * np.pi * 0.3 * t)
    noisy = clean + rng.normal(0, 1.0, t.shape)
    lm = np.zeros((200, 68, 2), np.float32)
    lm[:, 5, 1] = noisy
    got = smooth_landmarks(lm, fps=30.0, min_cutoff=1.0, beta=0.05)
    ref = _one_euro_reference(lm[:, 5, 1].astype(np.float64), 30.0, 1.0, 0.05, 1.0)
    np.testing.assert_allclose(got[:, 5, 1], ref, rtol=0, atol=1e-4)
    assert np.std(np.diff(got[20:, 5, 1] - clean[20:])) < 0.5 * np.std(np.diff(noisy[20:] - clean[20:]))
    f = OneEuroFilter(30.0)
    assert np.isnan(f(np.full(3, np.nan))).all()  # no face: passes NaN, restarts
    np.testing.assert_array_equal(f(np.ones(3)), np.ones(3))
    with pytest.raises(FacesynthError, match="One Euro"):
        OneEuroFilter(0.0)


def test_app_helpers():
    assert parse_size("320x240") == (320, 240)
    with pytest.raises(FacesynthError, match="WxH"):
        parse_size("big")
    lm = driving_landmarks(seed=9, n=3)
    w, h = default_size(lm)
    assert w >= lm[..., 0].max() and h >= lm[..., 1].max() and w % 2 == 0
    assert latency_summary([(0.001, 0.002)] * 10)["model_ms"]["p50"] == 1.0


def _read_video(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            return frames
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))


def test_app_writes_video_matching_torch(model_path, tmp_path):
    from facesynth.cli import main
    from facesynth.compositing import composite as torch_side_composite

    syn = synthetic_synthesizer("linear")
    lm = driving_landmarks(seed=10, n=8)
    lm[3] = np.nan  # a frame without a face: background only
    np.save(tmp_path / "lm.npy", lm)
    out, sheet = tmp_path / "out.mp4", tmp_path / "sheet.png"
    args = ["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(out),
            "--size", "240x220", "--side-by-side", "--no-progress", "--contact-sheet", str(sheet)]
    assert main(args) == 0
    frames = _read_video(out)
    assert len(frames) == 8 and frames[0].shape == (220, 480, 3)
    assert cv2.imread(str(sheet)) is not None
    # the frames the app encodes equal the torch synthesizer + composite (before lossy encoding)
    bg = np.full((220, 240, 3), 128, np.uint8)
    ours = list(render_frames(Renderer(model_path), lm, bg))
    np.testing.assert_array_equal(ours[3], bg)
    with torch.no_grad():
        crop, mask, place = syn(torch.from_numpy(np.where(np.isnan(lm), lm[2], lm)))
    for i in (0, 5, 7):
        ref = torch_side_composite(crop[i].permute(1, 2, 0).numpy(), mask[i, 0].numpy(), place[i].numpy().astype(np.float64), bg)
        assert np.abs(ours[i].astype(int) - ref.astype(int)).max() <= 1
        decoded = frames[i][:, 240:].astype(float)
        assert 10 * np.log10(255**2 / np.mean((decoded - ref) ** 2)) > 28  # mp4v is lossy
    # --smooth runs; --video without the ingest extra or a bad file is a clear error
    assert main(args[:-2] + ["--smooth"]) == 0
    assert main(["app", "--model", str(model_path), "--video", str(tmp_path / "none.mp4"), "--out", str(tmp_path / "x.mp4")]) == 2
    assert not (tmp_path / "x.mp4").exists()


def test_app_on_lp_d6_matches_torch(shared_clip_dir, tmp_path):
    """``facesynth app`` driven by lp_d6 landmarks with a model fitted on other lp_d6 frames,
    the real video beside it: the frames it encodes equal torch's rendering + composite."""
    from facesynth.cli import main
    from facesynth.compositing import composite as torch_side_composite
    from facesynth.data import load_sequence
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.sadm.quantize import quantize_synthesizer

    clip = shared_clip_dir("lp_d6")
    seq = load_sequence(clip)
    syn = quantize_synthesizer(real_linear_synthesizer(seq, np.arange(0, 240, 6)))[0]  # as the default export
    model_path = export_synthesizer(syn, tmp_path / "lp_d6.onnx")
    lm = seq.landmarks[:12].astype(np.float32)  # the app reads the first frames of the driver video
    np.save(tmp_path / "lm.npy", lm)
    out, sheet = tmp_path / "out.mp4", tmp_path / "sheet.png"
    assert main(["app", "--model", str(model_path), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(out),
                 "--size", "480x480", "--side-by-side", "--driver-video", str(clip / "video.mp4"),
                 "--no-progress", "--contact-sheet", str(sheet)]) == 0
    frames = _read_video(out)
    assert len(frames) == 12 and frames[0].shape == (480, 960, 3)
    assert cv2.imread(str(sheet)) is not None
    bg = np.full((480, 480, 3), 128, np.uint8)
    ours = list(render_frames(Renderer(model_path), lm, bg))
    with torch.no_grad():
        crop, mask, place = syn(torch.from_numpy(lm))
    for i in range(0, 12, 3):
        ref = torch_side_composite(crop[i].permute(1, 2, 0).numpy(), mask[i, 0].numpy(), place[i].numpy().astype(np.float64), bg)
        # the seam's alpha is made in the crop's pixels (facesynth.compositing): where ONNX Runtime's
        # placement and torch's differ in their last bits, OpenCV's 1/32-pixel warp grid rounds a
        # few pixels on the face's outline differently (measured: at most 3 levels)
        d = np.abs(ours[i].astype(int) - ref.astype(int)).max(-1)
        assert d.max() <= 3 and (d > 1).mean() < 1e-3
        assert (ref != bg).any(axis=2).mean() > 0.1  # a face was drawn
        decoded = frames[i][:, 480:].astype(float)
        assert 10 * np.log10(255**2 / np.mean((decoded - ref) ** 2)) > 28  # mp4v is lossy
        # the driver half is the real video frame
        real = seq.frame(i)
        assert 10 * np.log10(255**2 / np.mean((frames[i][:, :480].astype(float) - real) ** 2)) > 25

