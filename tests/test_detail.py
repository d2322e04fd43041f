"""Example-based detail (facesynth.model.detail): the retrieval against a brute-force numpy
nearest neighbour, the bank against its definition (OpenCV blur, int8 codes), its continuity,
the artifact, and the exported graphs against the torch path."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch
from _faces import face_sequence_arrays

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.detail import MEDIAN_EPS, MEDIAN_STEPS, DetailTransfer, check_detail


def random_bank(rng, n=40, points=(3, 5, 7), channels=3, n_pixels=50, cols=None):
    cols = np.sort(rng.choice(n_pixels, 20, replace=False)) if cols is None else cols
    return {"detail_keys": rng.normal(size=(n, 2 * len(points))).astype(np.float32),
            "detail_codes": rng.integers(-127, 128, (n, channels * len(cols))).astype(np.int8),
            "detail_scale": rng.uniform(0.001, 0.01, n).astype(np.float32),
            "detail_columns": cols.astype(np.int64), "detail_points": np.asarray(points, np.int64)}


def brute_force(bank, k, strength, texture, aligned):
    """The same blend written with a full numpy sort, float64."""
    keys = bank["detail_keys"].astype(np.float64)
    high = bank["detail_codes"].astype(np.float64) * bank["detail_scale"][:, None].astype(np.float64)
    cols = bank["detail_columns"]
    out = texture.astype(np.float64).copy()
    for b in range(len(texture)):
        q = aligned[b, bank["detail_points"]].reshape(-1).astype(np.float64)
        d = ((keys - q) ** 2).sum(1)
        order = np.argsort(d, kind="stable")
        w = np.maximum(0, 1 / (d[order[:k]] + 1e-12) - 1 / (d[order[k]] + 1e-12))
        w /= w.sum()
        add = (w[:, None] * high[order[:k]]).sum(0).reshape(texture.shape[1], len(cols))
        if bank.get("detail_median", [False])[0]:  # per pixel, Weiszfeld steps towards the weighted median
            rows = high[order[:k]].reshape(k, texture.shape[1], len(cols))
            for j in range(len(cols)):
                m = add[:, j].copy()
                for _ in range(MEDIAN_STEPS):
                    u = np.array([w[i] / np.sqrt(np.sum((rows[i, :, j] - m) ** 2) + MEDIAN_EPS ** 2) for i in range(k)])
                    m = (u[:, None] * rows[:, :, j]).sum(0) / u.sum()
                add[:, j] = m
        replace = float(bank.get("detail_replace", [False])[0])  # a texture bank: towards the frames' own pixels
        add = add - bank.get("detail_alpha", np.full(len(cols), replace)) * out[b][:, cols]
        reach = float(bank.get("detail_reach", [0.0])[0])
        if reach > 0:  # faded out far from every key
            add = add / (1 + (d[order[0]] / reach) ** 2)
        out[b][:, cols] += strength * add
    return np.clip(out, 0, 1)


def test_retrieval_equals_a_brute_force_nearest_neighbour():
    rng = np.random.default_rng(0)
    bank = random_bank(rng)
    tex = rng.uniform(0.1, 0.9, (6, 3, 50)).astype(np.float32)
    aligned = rng.normal(size=(6, 10, 2)).astype(np.float32)
    for k, s in ((1, 1.0), (4, 0.5), (7, 1.0)):
        got = DetailTransfer(bank, k, s, 50)(torch.from_numpy(tex), torch.from_numpy(aligned)).numpy()
        assert got == pytest.approx(brute_force(bank, k, s, tex, aligned), abs=1e-5)
    texture_bank = {**bank, "detail_replace": np.asarray([True])}
    got = DetailTransfer(texture_bank, 4, 0.5, 50)(torch.from_numpy(tex), torch.from_numpy(aligned)).numpy()
    assert got == pytest.approx(brute_force(texture_bank, 4, 0.5, tex, aligned), abs=1e-5)
    # a texture bank blended by the per-pixel median, feathered at its edge
    median_bank = {**texture_bank, "detail_median": np.asarray([True]),
                   "detail_alpha": rng.uniform(0, 1, 20).astype(np.float32),
                   "detail_reach": np.asarray([5.0], np.float32)}
    for k in (1, 4, 7):
        got = DetailTransfer(median_bank, k, 0.8, 50)(torch.from_numpy(tex), torch.from_numpy(aligned)).numpy()
        assert got == pytest.approx(brute_force(median_bank, k, 0.8, tex, aligned), abs=1e-5)
    # pixels outside the bank's columns are untouched
    got = DetailTransfer(bank, 4, 1.0, 50)(torch.from_numpy(tex), torch.from_numpy(aligned)).numpy()
    out = np.setdiff1d(np.arange(50), bank["detail_columns"])
    assert np.array_equal(got[:, :, out], tex[:, :, out])


def test_the_median_votes_down_an_outlier():
    """Three dark mouths (weight 0.7) and one with teeth (0.3): the mean is a grey smear, the
    median blend stays within a few hundredths of the dark colour."""
    from facesynth.model.detail import weighted_median

    dark, teeth = np.array([0.25, 0.08, 0.08]), np.array([0.9, 0.88, 0.85])
    rng = np.random.default_rng(3)
    rows = np.stack([dark + rng.normal(0, 0.01, 3) for _ in range(3)] + [teeth])[None, :, :, None]
    w = torch.tensor([[0.3, 0.2, 0.2, 0.3]])
    med = weighted_median(torch.from_numpy(rows.astype(np.float32)), w)[0, :, 0].numpy()
    mean = (w.numpy()[0, :, None] * rows[0, :, :, 0]).sum(0)
    assert np.abs(med - dark).max() < 0.04
    assert np.abs(mean - dark).max() > 0.15


@pytest.mark.parametrize("median", [False, True])
def test_the_blend_is_continuous_when_the_neighbours_change(median):
    """Along a path of shapes the set of k nearest frames changes many times, yet the output
    moves by no more than a step's share: no popping (also with the median blend)."""
    rng = np.random.default_rng(1)
    bank = random_bank(rng, n=30)
    if median:
        bank.update(detail_replace=np.asarray([True]), detail_median=np.asarray([True]),
                    detail_reach=np.asarray([3.0], np.float32))
    det = DetailTransfer(bank, 3, 1.0, 50)
    tex = torch.full((1, 3, 50), 0.5)
    a, b = rng.normal(size=(2, 10, 2)).astype(np.float32)
    t = np.linspace(0, 1, 2001, dtype=np.float32)
    path = torch.from_numpy(a[None] * (1 - t[:, None, None]) + b[None] * t[:, None, None])
    with torch.no_grad():
        idx, _ = det.weights(path)
        out = det(tex.expand(len(t), -1, -1), path).numpy().reshape(len(t), -1)
    changes = int((np.sort(idx.numpy(), 1)[1:] != np.sort(idx.numpy(), 1)[:-1]).any(1).sum())
    assert changes >= 3
    step = np.abs(np.diff(out, axis=0)).max()
    jump = np.abs(bank["detail_codes"].astype(np.float32) * bank["detail_scale"][:, None]).max()
    assert step < 0.05 * jump


@pytest.fixture(scope="module")
def interior():
    """A face model whose bank holds the mouth interior's own pixels, median-blended, feathered."""
    frames, lm = face_sequence_arrays(n=24, seed=2)
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    cfg = FaceModelConfig(reference_width=64, appearance_variance=0.95, detail=1.0, detail_k=3, detail_parts="interior",
                          detail_band="texture", detail_blend="median", detail_feather=1.0, detail_reach=10.0)
    model, tex = FaceModel.fit_with_textures(seq, cfg, progress=False)
    return seq, model, tex


def test_the_interior_bank_holds_the_frames_pixels_under_a_feathered_mask(interior):
    from facesynth.landmarks import face_region_masks, ibug68_view

    seq, model, tex = interior
    bank = model.detail_bank
    cols, alpha = bank["detail_columns"], bank["detail_alpha"]
    # the frames' own texture on those pixels times their weight, to int8 rounding
    want = (alpha * tex[5].reshape(model.n_channels, -1)[:, cols]).reshape(-1)
    got = bank["detail_codes"][5].astype(np.float64) * bank["detail_scale"][5]
    assert np.abs(got - want).max() <= 0.51 * bank["detail_scale"][5] + 1e-6
    # the weights: the interior's mask blurred (OpenCV), 1 inside it, fading over the lips
    h, w = model.reference.size
    index = model.sampler().mask_index.numpy()
    inside = np.zeros(h * w, bool)
    inside[index] = True
    mouth = face_region_masks(ibug68_view(model.reference.points.astype(np.float64)), (h, w),
                              within=inside.reshape(h, w))["mouth_interior"].reshape(-1)
    blur = cv2.GaussianBlur(mouth.reshape(h, w).astype(np.float32), (0, 0), model.reference.size[1] / 128)
    blur = blur.reshape(-1)[index]
    assert alpha == pytest.approx(np.minimum(blur[cols] / blur.max(), 1), abs=1e-5)
    assert set(np.flatnonzero(mouth[index])) <= set(cols.tolist()) and len(cols) > mouth[index].sum()
    # the reach: 10 times the 90th percentile of the keys' nearest-neighbour squared distances (brute force)
    keys = bank["detail_keys"].astype(np.float64)
    nn = [min(((keys[i] - keys[j]) ** 2).sum() for j in range(len(keys)) if j != i) for i in range(len(keys))]
    assert float(bank["detail_reach"][0]) == pytest.approx(10 * np.quantile(nn, 0.9), rel=1e-5)
    # keyed by the inner lips only
    assert np.array_equal(bank["detail_points"], np.sort(get_scheme(model.scheme).region("inner_lips")))


def test_the_mixed_bank_holds_the_interior_pixels_and_the_lips_high_band(interior):
    """``detail_band=interior`` on the mouth: per pixel the frames' own texture weighted by the
    feathered interior mask, the high band (OpenCV blur) by the rest; the prediction is replaced
    by that same weight."""
    from facesynth.model.detail import fit_detail_bank, high_band, part_columns

    seq, model, tex = interior
    model = dataclasses.replace(model, config=dataclasses.replace(model.config, detail_parts="mouth",
                                                                  detail_band="interior", detail_blend="mean"))
    bank, report = fit_detail_bank(model, seq.landmarks, tex)
    px = model.reference.size[1] / 128
    cols, part = part_columns(model, "mouth", px)
    icols, iw = part_columns(model, "mouth", px, names=("mouth_interior",))
    weight = np.zeros(model.n_pixels)
    weight[icols] = iw
    alpha = weight[cols]
    assert np.array_equal(bank["detail_columns"], cols) and 0 < alpha.mean() < 1
    assert bank["detail_alpha"] == pytest.approx(part * alpha, abs=1e-6)
    own = tex[5].reshape(model.n_channels, -1)[:, cols]
    high = high_band(model, tex[5:6], report["sigma_px"])[0][:, cols]
    want = (part * (alpha * own + (1 - alpha) * high)).reshape(-1)
    got = bank["detail_codes"][5].astype(np.float64) * bank["detail_scale"][5]
    assert np.abs(got - want).max() <= 0.51 * bank["detail_scale"][5] + 1e-6
    assert np.array_equal(bank["detail_points"], np.sort(np.concatenate(
        [get_scheme(model.scheme).region(r) for r in ("outer_lips", "inner_lips")])))


def test_a_closed_reference_mouth_gives_no_interior_bank(interior):
    from facesynth.model.detail import fit_detail_bank

    seq, model, tex = interior
    pts = model.reference.points.copy()
    pts[[65, 66, 67]] = pts[[63, 62, 61]]  # the inner lips closed: the interior has no pixel
    closed = dataclasses.replace(model, reference=dataclasses.replace(model.reference, points=pts))
    with np.errstate(invalid="ignore"):  # the closed mouth's triangles are degenerate
        bank, report = fit_detail_bank(closed, seq.landmarks, tex)
    assert bank is None and report["pixels"] == 0


def test_the_interior_graph_matches_torch(interior, tmp_path):
    from facesynth.onnx.synthesis import check_export, export_synthesizer
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq, model, tex = interior
    reg = REGISTRY["linear"].fit(model.shape_params(seq.landmarks, clamp=True), model.appearance_params(tex), seed=0)
    syn = Synthesizer(model, GlobalAppearance(model, reg)).eval()
    assert syn.detail is not None and syn.detail.median and (syn.detail.alpha < 1).any()
    assert check_export(syn, export_synthesizer(syn, tmp_path / "m.onnx"), seq.landmarks[:6]) < 1e-4


@pytest.fixture(scope="module")
def detailed():
    frames, lm = face_sequence_arrays(n=24, seed=2)
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    cfg = FaceModelConfig(reference_width=64, appearance_variance=0.95, detail=1.0, detail_k=3)
    model, tex = FaceModel.fit_with_textures(seq, cfg, progress=False)
    return seq, model, tex


def test_the_bank_holds_each_frames_high_band(detailed):
    seq, model, tex = detailed
    bank = model.detail_bank
    report = model.meta["detail"]
    assert report["frames"] == len(bank["detail_keys"]) == len(seq)  # fewer than BANK_FRAMES: all of them
    assert report["bytes"] == sum(v.nbytes for v in bank.values())
    # the high band by its definition: the texture minus its mask-normalised Gaussian blur (OpenCV)
    sigma = report["sigma_px"]
    h, w = model.reference.size
    index = model.sampler().mask_index.numpy()
    m = np.zeros(h * w, np.float64)
    m[index] = 1
    den = cv2.GaussianBlur(m.reshape(h, w), (0, 0), sigma)
    img = model.texture_images(tex[5:6])[0].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):  # den is 0 far outside the face: those pixels are dropped
        want = (img - cv2.GaussianBlur(img, (0, 0), sigma) / den[..., None]).reshape(h * w, -1)[index].T
    want = want[:, bank["detail_columns"]].reshape(-1)
    got = bank["detail_codes"][5].astype(np.float64) * bank["detail_scale"][5]
    assert np.abs(got - want).max() <= 0.51 * bank["detail_scale"][5] + 1e-6  # int8 rounding
    # the keys are the frames' aligned key points, as the synthesiser aligns them
    aligned, _ = model.align(model.denoise(seq.landmarks))
    assert bank["detail_keys"] == pytest.approx(aligned[:, bank["detail_points"]].reshape(len(seq), -1), abs=1e-5)


def test_a_training_frame_retrieves_its_own_detail(detailed):
    """At a training frame's own shape its key is at distance 0: the blend is its own high band."""
    seq, model, tex = detailed
    det = DetailTransfer(model.detail_bank, 3, 1.0, model.n_pixels)
    aligned, _ = model.align(model.denoise(seq.landmarks[7:8]))
    idx, w = det.weights(torch.from_numpy(aligned.astype(np.float32)))
    assert int(idx[0, 0]) == 7 and float(w[0, 0]) == pytest.approx(1.0, abs=1e-4)


def test_the_artifact_and_the_exported_graph_keep_the_detail(detailed, tmp_path):
    from facesynth.model.artifact import load_face_model, save_face_model
    from facesynth.onnx.synthesis import check_export, export_synthesizer
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq, model, tex = detailed
    save_face_model(model, tmp_path / "fm")
    back = load_face_model(tmp_path / "fm")
    for k, v in model.detail_bank.items():
        assert np.array_equal(back.detail_bank[k], v) and back.detail_bank[k].dtype == v.dtype
    x = model.shape_params(seq.landmarks, clamp=True)
    reg = REGISTRY["linear"].fit(x, model.appearance_params(tex), seed=0)
    syn = Synthesizer(back, GlobalAppearance(back, reg)).eval()
    plain = Synthesizer(dataclasses.replace(back, detail_bank=None), GlobalAppearance(back, reg)).eval()
    lm = torch.from_numpy(seq.landmarks[:4])
    with torch.no_grad():
        t, t0 = syn.texture(lm), plain.texture(lm)
        aligned, _ = syn.encoder(lm)
    # the synthesiser adds exactly what the retrieval gives, on the bank's pixels
    want = DetailTransfer(back.detail_bank, 3, 1.0, back.n_pixels)(t0, aligned)
    assert t.numpy() == pytest.approx(want.numpy(), abs=1e-6)
    assert not np.allclose(t.numpy(), t0.numpy())
    path = export_synthesizer(syn, tmp_path / "m.onnx")
    assert check_export(syn, path, seq.landmarks[:6]) < 1e-4
    import onnx

    ops = {n.op_type for n in onnx.load(str(path)).graph.node}
    assert "TopK" in ops


def test_bad_settings_are_refused():
    for field, value in (("detail", 1.5), ("detail_k", 0), ("detail_parts", "nose"), ("detail_sigma", 0.0),
                         ("detail_band", "low"), ("detail_blend", "mode"), ("detail_feather", -1.0),
                         ("detail_reach", -1.0)):
        with pytest.raises(FacesynthError, match=f"model.{field}"):
            check_detail(dataclasses.replace(FaceModelConfig(), **{field: value}))


@pytest.mark.parametrize("settings", [{}, {"detail_parts": "interior", "detail_band": "texture", "detail_blend": "median",
                                       "detail_feather": 1.0, "detail_reach": 10.0}], ids=["high", "interior"])
def test_the_talking_head_graph_carries_the_detail(shared_clip_dir, tmp_path, settings):
    """A talking head with a detail bank matches the numpy pipeline on its face-only file (which
    test_the_artifact_and_the_exported_graph_keep_the_detail holds to the torch path), and
    the bank changes the frames."""
    from facesynth.data import load_sequence, temporal_split
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.onnx.talking_head import export_talking_head
    from facesynth.regressors import REGISTRY
    from facesynth.runtime import Reenactor
    from facesynth.runtime.reenact import driver_neutral_of
    from facesynth.runtime.talking_head import TalkingHead
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq = load_sequence(shared_clip_dir("lp_d10"))
    train, _ = temporal_split(len(seq))
    rows = train[::3]
    model = FaceModel.fit(seq, FaceModelConfig(detail=1.0, **settings), rows=rows, progress=False)
    assert model.detail_bank is not None
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows), clamp=True)
    syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
    meta = avatar_metadata(syn, seq.landmarks[train], train, seq)
    export_synthesizer(syn, tmp_path / "face.onnx", meta)
    export_talking_head(syn, meta, tmp_path / "head.onnx")
    plain = syn.with_appearance(syn.appearance)
    plain.detail = None
    export_talking_head(plain, meta, tmp_path / "plain.onnx")
    lm = np.load(shared_clip_dir("lp_d13") / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    th = TalkingHead(tmp_path / "head.onnx", driver_neutral=neutral)
    th0 = TalkingHead(tmp_path / "plain.onnx", driver_neutral=neutral)
    ref = Reenactor(tmp_path / "face.onnx", driver_neutral=neutral, feather=th.feather, full_frame=True)
    worst, moved = 0, 0
    for i in np.linspace(0, len(lm) - 1, 6).astype(int):
        want, _ = ref.step(lm[i])
        got, _ = th.step(lm[i])
        worst = max(worst, int(np.abs(got.astype(int) - want).max()))
        moved += int((np.abs(got.astype(int) - th0.step(lm[i])[0]) > 2).sum())
    assert worst <= 2
    assert moved > 0
