"""The per-subject restoration filter (facesynth.model.restore): the render-time filter against
OpenCV, the least-squares fit against a direct solve, the artifact and the exported graph."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch
from _faces import face_sequence_arrays

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.restore import (
    GUARD_DB,
    STRIPS,
    Restore,
    apply_path,
    choose_strength,
    mean_offset,
    path_curve,
    path_parts,
    strength_curve,
    with_strength,
)


@pytest.mark.parametrize(("h", "w", "size", "channels"), [(40, 52, 5, 3), (9, 30, 7, 3), (151, 77, 7, 1), (64, 64, 3, 3)])
def test_restore_equals_opencv(h, w, size, channels):
    """Fill (a box mean of the face pixels around each outside pixel) then a correlation with
    the kernel, clamped and cut to the face: cv2.boxFilter and cv2.filter2D, zero borders. Heights
    below, at and off a multiple of the strips (:data:`facesynth.model.restore.STRIPS`), and a face
    that touches the image's edge."""
    rng = np.random.default_rng(h)
    mask = np.zeros((h, w), np.float32)
    cv2.ellipse(mask, (w // 2, h // 2), (w // 2 - 2, h // 2 + 1), 0, 0, 360, 1.0, -1)
    img = rng.uniform(0, 1, (h, w, channels)).astype(np.float32) * mask[..., None]
    kernel = rng.normal(0, 0.2, (size, size)).astype(np.float32)
    kernel[size // 2, size // 2] += 1.0
    got = Restore(kernel)(torch.from_numpy(img).permute(2, 0, 1)[None], torch.from_numpy(mask)[None, None])
    got = got[0].permute(1, 2, 0).numpy()
    box = dict(ddepth=-1, ksize=(size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    num = cv2.boxFilter(img.astype(np.float64), **box).reshape(img.shape)
    den = np.maximum(cv2.boxFilter(mask.astype(np.float64), **box), 1.0)
    filled = img + (1 - mask[..., None]) * num / den[..., None]
    want = cv2.filter2D(filled, -1, kernel.astype(np.float64), borderType=cv2.BORDER_CONSTANT).reshape(filled.shape)
    want = np.clip(want, 0, 1) * mask[..., None]
    assert got == pytest.approx(want, abs=1e-5)
    assert Restore(kernel).fill(torch.from_numpy(img).permute(2, 0, 1)[None], torch.from_numpy(mask)[None, None])[0] \
        .permute(1, 2, 0).numpy() == pytest.approx(filled, abs=1e-5)
    # the identity kernel leaves the face as it was
    same = Restore(np.pad(np.ones((1, 1), np.float32), 1))(torch.from_numpy(img).permute(2, 0, 1)[None],
                                                             torch.from_numpy(mask)[None, None])
    assert same[0].permute(1, 2, 0).numpy() == pytest.approx(img, abs=1e-6)


@pytest.fixture(scope="module")
def restored(tmp_path_factory):
    frames, lm = face_sequence_arrays(n=24, seed=1)
    # the real frames are sharper than what the render path gives back: an unsharp mask
    sharp = np.stack([np.clip(1.8 * f.astype(np.float32) - 0.8 * cv2.GaussianBlur(f, (0, 0), 1.2), 0, 255).astype(np.uint8)
                      for f in frames])
    seq = FaceSequence.from_arrays(lm, ArrayFrames(sharp), name="unit")
    cfg = FaceModelConfig(reference_width=64, appearance_variance=0.95, restore=True)
    model, tex = FaceModel.fit_with_textures(seq, cfg, progress=False)
    return seq, model, tex


def test_fit_chooses_a_filter_that_beats_none_held_out(restored):
    seq, model, tex = restored
    report = model.meta["restore"]
    assert model.restore_kernel is not None and model.restore_kernel.shape == (report["size"],) * 2
    errs = report["held_out_rms"]
    assert errs[str(report["size"])] < errs["1"]
    # the filtered render of the frame's own texture is closer to the real frame than the unfiltered one
    plain = dataclasses.replace(model, restore_kernel=None)
    rows = np.arange(0, 24, 5)
    err = {}
    for name, m in (("restored", model), ("plain", plain)):
        crops, masks, places = m.render(tex[rows], seq.landmarks[rows])
        e = []
        for j, frame in enumerate(seq.iter_frames(rows)):
            h, w = frame.shape[:2]
            face = cv2.warpAffine(crops[j], places[j], (w, h))
            inside = cv2.erode((cv2.warpAffine(masks[j], places[j], (w, h)) > 0.999).astype(np.uint8), np.ones((5, 5))) > 0
            e.append(((face * 255 - frame)[inside] ** 2).mean())
        err[name] = np.mean(e)
    assert err["restored"] < err["plain"]


def test_the_artifact_and_the_exported_graph_keep_the_filter(restored, tmp_path):
    from facesynth.model.artifact import load_face_model, save_face_model
    from facesynth.onnx.synthesis import check_export, export_synthesizer
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq, model, tex = restored
    save_face_model(model, tmp_path / "fm")
    back = load_face_model(tmp_path / "fm")
    assert np.array_equal(back.restore_kernel, model.restore_kernel)
    x = model.shape_params(seq.landmarks, clamp=True)
    reg = REGISTRY["linear"].fit(x, model.appearance_params(tex), seed=0)
    syn = Synthesizer(back, GlobalAppearance(back, reg)).eval()
    # the synthesiser renders what the face model renders
    with torch.no_grad():
        crop, _, _ = syn(torch.from_numpy(seq.landmarks[:4]))
        t = syn.texture(torch.from_numpy(seq.landmarks[:4])).reshape(4, -1).numpy()
    want = back.render(t, seq.landmarks[:4])[0]
    assert crop.permute(0, 2, 3, 1).numpy() == pytest.approx(want, abs=1e-5)
    path = export_synthesizer(syn, tmp_path / "m.onnx")
    assert check_export(syn, path, seq.landmarks[:6]) < 1e-4
    import onnx

    # depthwise Convs over the strips: the fill's box sums along x and y (image and mask), the filter (image)
    groups = sorted(next(a.i for a in n.attribute if a.name == "group")
                    for n in onnx.load(str(path)).graph.node if n.op_type == "Conv")
    assert groups == [3 * STRIPS, 4 * STRIPS, 4 * STRIPS]


def _pasted_sse(model, textures, seq, rows):
    """Per frame: the squared error (0-1 scale) of the rendered face pasted into the real frame,
    over the face where the paste reads only face pixels (eroded by the fit's 2 px feather)."""
    crops, masks, places = model.render(textures, seq.landmarks[rows])
    out = []
    for j, frame in enumerate(seq.iter_frames(rows)):
        h, w = frame.shape[:2]
        face = cv2.warpAffine(crops[j], places[j], (w, h), flags=cv2.INTER_LINEAR)
        inside = cv2.erode((cv2.warpAffine(masks[j], places[j], (w, h)) > 0.999).astype(np.uint8), np.ones((5, 5))) > 0
        out.append(float(((face.astype(np.float64) - frame / 255.0)[inside] ** 2).sum()))
    return np.array(out)


def test_strength_zero_is_no_filter_and_one_is_the_kernel(restored):
    _, model, _ = restored
    k = model.restore_kernel
    zero = with_strength(k, 0.0)
    delta = np.zeros_like(k)
    delta[k.shape[0] // 2, k.shape[1] // 2] = 1
    assert np.array_equal(zero, delta)
    assert with_strength(k, 1.0) == pytest.approx(k, abs=1e-7)
    assert with_strength(k, 0.5) == pytest.approx((delta + k) / 2, abs=1e-7)
    rng = np.random.default_rng(3)
    mask = np.zeros((30, 30), np.float32)
    mask[5:25, 4:26] = 1
    img = torch.from_numpy(rng.uniform(0, 1, (1, 3, 30, 30)).astype(np.float32) * mask)
    assert Restore(zero)(img, torch.from_numpy(mask)[None, None]).numpy() == pytest.approx(img.numpy(), abs=1e-6)


def test_strength_curve_is_the_rendered_psnr_change_and_the_guard_holds(restored):
    """The closed-form curve (quadratic per frame in the strength) against rendering each strength
    through the face model (torch Restore, clamp and all) and pasting it with OpenCV; the chosen
    strength is the largest within the guard, and its rendered PSNR cost is within it."""
    seq, model, tex = restored
    plain = dataclasses.replace(model, restore_kernel=None)
    rows = np.arange(1, 24, 3)
    pred = np.clip(tex[rows] + np.random.default_rng(0).normal(0, 0.03, tex[rows].shape), 0, 1).astype(np.float32)
    strengths = np.linspace(0, 1, 11)
    curve = strength_curve(plain, seq, rows, pred, model.restore_kernel, strengths)
    assert curve[0] == pytest.approx(0.0, abs=1e-9)
    base = _pasted_sse(plain, pred, seq, rows)
    for i in (4, 10):
        m = dataclasses.replace(model, restore_kernel=with_strength(model.restore_kernel, strengths[i]))
        direct = float(np.mean(-10 * np.log10(_pasted_sse(m, pred, seq, rows) / base)))
        assert curve[i] == pytest.approx(direct, abs=0.02)
    for guard in (0.0, 0.05, 0.2):
        s = choose_strength(curve, strengths, guard)
        at = int(np.flatnonzero(strengths == s)[0])
        assert curve[at] >= -guard and (curve[at + 1 :] < -guard).all()
        m = dataclasses.replace(model, restore_kernel=with_strength(model.restore_kernel, s))
        assert float(np.mean(-10 * np.log10(_pasted_sse(m, pred, seq, rows) / base))) >= -guard - 0.02


def test_fit_matches_a_direct_least_squares_solve(restored):
    """The kernel from the summed normal equations equals numpy's lstsq on the stacked design
    (the ridge as extra rows pulling towards no filter) for the chosen size and ridge."""
    from facesynth.model.restore import FIT_FRAMES, SIZES, _designs, _taps, fit_restoration

    seq, model, tex = restored
    plain = dataclasses.replace(model, restore_kernel=None)
    rows = np.arange(24)
    kernel, report = fit_restoration(plain, seq, rows, tex)
    assert kernel is not None
    pick = np.unique(np.linspace(0, len(rows) - 1, min(FIT_FRAMES, len(rows))).round().astype(int))
    full = max(SIZES)
    taps = _taps(report["size"], full)
    parts = list(_designs(plain, seq, rows[pick], tex[pick], 2.0, full))
    a = np.concatenate([p[1] for p in parts])
    b = np.concatenate([p[2] for p in parts])
    lam = report["ridge"] * len(b) * float(np.mean(np.sum(a * a, 0))) / len(b)
    delta = (taps == full * full // 2).astype(np.float64)
    aa = np.concatenate([a[:, taps], np.sqrt(lam) * np.eye(len(taps))])
    bb = np.concatenate([b, np.sqrt(lam) * delta])
    want = np.linalg.lstsq(aa, bb, rcond=None)[0]
    assert kernel.reshape(-1) == pytest.approx(want, abs=1e-4)


def test_sadm_fit_scales_the_filter_within_the_guard(restored):
    from facesynth.sadm.fit import SADMConfig, fit_sadm

    seq, model, tex = restored
    m = dataclasses.replace(model)
    full = m.restore_kernel.copy()
    sadm = fit_sadm(m, seq, np.arange(24), tex, "linear", {}, SADMConfig(region_shrink=False, val_fraction=0.25,
                                                                          restore_guard=GUARD_DB))
    r = sadm.restore
    assert 0.0 <= r["strength"] <= 1.0 and r["psnr_change_db"] >= -r["guard_db"] and r["val_frames"] == 6
    # every slice (blocks of 6 rows at the end of the 18 training rows, each after a gap of 6) within the guard
    assert [sl["val_rows"] for sl in r["slices"]] == [[12, 18], [18, 24]] and r["fit_frames"] == 12
    assert r["psnr_change_db"] == min(sl["psnr_change_db"] for sl in r["slices"]) >= -r["guard_db"]
    # the model is at the chosen point of the path: the crop's filter at the variation's strength, the rest
    # of the mean's part as the texture offset
    assert (r["mean_strength"], r["strength"]) == path_parts(r["path"])
    want = dataclasses.replace(model)
    apply_path(want, full, r["path"])
    for got, ref in ((m.restore_kernel, want.restore_kernel), (m.restore_offset, want.restore_offset)):
        assert (got is None and ref is None) or np.array_equal(got, ref)
    off = dataclasses.replace(model)
    fit_sadm(off, seq, np.arange(24), tex, "linear", {}, SADMConfig(region_shrink=False, restore_guard=None))
    assert np.array_equal(off.restore_kernel, full) and off.restore_offset is None
    # a model at the mean's part alone (restore_variation=0) is guarded too, along the path's first half
    mean_only = dataclasses.replace(model, config=dataclasses.replace(model.config, restore_variation=0.0))
    apply_path(mean_only, full, 1.0)
    r0 = fit_sadm(mean_only, seq, np.arange(24), tex, "linear", {},
                  SADMConfig(region_shrink=False, val_fraction=0.25, restore_guard=GUARD_DB)).restore
    assert r0 is not None and r0["path"] <= 1.0 and r0["strength"] == 0.0 and mean_only.restore_kernel is None
    assert len(r0["curve_db"]) == 41 and r0["psnr_change_db"] >= -r0["guard_db"]


def test_the_mean_offset_is_the_crop_filter_on_the_rendered_mean(restored):
    """restore_variation=0: the filter's part on the mean texture, added to the texture in the
    reference frame before the warp, renders what the crop's filter does to the rendered mean added to
    the unfiltered render (the filter is linear; the two differ by the warp's resampling of the
    filtered mean); no filter is left in the model."""
    seq, model, tex = restored
    full = model.restore_kernel
    plain = dataclasses.replace(model, restore_kernel=None, restore_offset=None)
    mean_only = dataclasses.replace(plain)
    apply_path(mean_only, full, 1.0)
    assert mean_only.restore_kernel is None and mean_only.restore_offset.shape == (tex.shape[1],)
    assert mean_only.restore_offset == pytest.approx(mean_offset(plain, full))
    rows = np.arange(2, 24, 4)
    got = mean_only.render(tex[rows], seq.landmarks[rows])[0]
    img, mask, _ = plain.render(tex[rows], seq.landmarks[rows])
    mimg = plain.render(np.repeat(model.appearance_pca.mean[None], len(rows), 0), seq.landmarks[rows])[0]
    m = torch.from_numpy(mask)[:, None]
    mt = torch.from_numpy(mimg).permute(0, 3, 1, 2)
    filtered = Restore(full)(mt, m) - mt * m
    want = np.clip(img + filtered.permute(0, 2, 3, 1).numpy(), 0, 1) * mask[..., None]
    inside = cv2.erode(mask.transpose(1, 2, 0), np.ones((7, 7))).transpose(2, 0, 1) > 0.5  # away from the mask's edge
    diff = np.abs(got - want)[inside]
    change = np.abs(got - img)[inside]
    assert diff.mean() < 0.1 * change.mean() and diff.mean() < 1 / 255


def test_path_curve_is_the_rendered_psnr_change_and_ends_at_the_filter(restored):
    """The path's closed-form curve against rendering each point through the face model (offset,
    torch Restore, clamps) and pasting it with OpenCV; its end is strength_curve's full strength,
    its middle the mean's part alone."""
    seq, model, tex = restored
    full = model.restore_kernel
    plain = dataclasses.replace(model, restore_kernel=None, restore_offset=None)
    rows = np.arange(1, 24, 3)
    pred = np.clip(tex[rows] + np.random.default_rng(0).normal(0, 0.03, tex[rows].shape), 0, 1).astype(np.float32)
    points = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    for textures in (pred, tex[rows]):  # noisy predictions (the variation's part costs), the frames' own (all gains)
        curve = path_curve(plain, seq, rows, textures, full, points)
        assert curve[0] == pytest.approx(0.0, abs=1e-9)
        assert curve[-1] == pytest.approx(strength_curve(plain, seq, rows, textures, full, np.array([1.0]))[0], abs=1e-9)
        base = _pasted_sse(plain, textures, seq, rows)
        for i in (1, 2, 3, 4):
            m = dataclasses.replace(plain)
            apply_path(m, full, points[i])
            direct = float(np.mean(-10 * np.log10(_pasted_sse(m, textures, seq, rows) / base)))
            assert curve[i] == pytest.approx(direct, abs=0.005)
    assert curve[2] > 0.02  # the mean's part alone gives the frames' own textures back some of their detail


def test_mean_only_model_keeps_no_filter_in_its_artifact_and_graph(restored, tmp_path):
    import onnx

    from facesynth.model.artifact import load_face_model, save_face_model
    from facesynth.onnx.synthesis import check_export, export_synthesizer
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq, model, tex = restored
    m = dataclasses.replace(model)
    apply_path(m, model.restore_kernel, 1.0)
    save_face_model(m, tmp_path / "fm")
    back = load_face_model(tmp_path / "fm")
    assert back.restore_kernel is None and np.array_equal(back.restore_offset, m.restore_offset)
    x = back.shape_params(seq.landmarks, clamp=True)
    syn = Synthesizer(back, GlobalAppearance(back, REGISTRY["linear"].fit(x, back.appearance_params(tex), seed=0))).eval()
    with torch.no_grad():
        crop, _, _ = syn(torch.from_numpy(seq.landmarks[:4]))
        t = syn.texture(torch.from_numpy(seq.landmarks[:4])).reshape(4, -1).numpy()
    assert crop.permute(0, 2, 3, 1).numpy() == pytest.approx(back.render(t, seq.landmarks[:4])[0], abs=1e-5)
    path = export_synthesizer(syn, tmp_path / "m.onnx")
    assert check_export(syn, path, seq.landmarks[:6]) < 1e-4
    assert not [n for n in onnx.load(str(path)).graph.node if n.op_type == "Conv"]


def test_restore_variation_outside_its_range_is_refused():
    from facesynth.errors import FacesynthError

    frames, lm = face_sequence_arrays(n=6, seed=2)
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    with pytest.raises(FacesynthError, match="restore_variation"):
        FaceModel.fit(seq, FaceModelConfig(reference_width=48, restore=True, restore_variation=1.5), progress=False)
