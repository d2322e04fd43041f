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
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.detail import DetailTransfer, check_detail


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
        if bank.get("detail_replace", [False])[0]:  # a texture bank: towards the frames' own pixels
            add = add - out[b][:, cols]
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
    # pixels outside the bank's columns are untouched
    got = DetailTransfer(bank, 4, 1.0, 50)(torch.from_numpy(tex), torch.from_numpy(aligned)).numpy()
    out = np.setdiff1d(np.arange(50), bank["detail_columns"])
    assert np.array_equal(got[:, :, out], tex[:, :, out])


def test_the_blend_is_continuous_when_the_neighbours_change():
    """Along a path of shapes the set of k nearest frames changes many times, yet the output
    moves by no more than a step's share: no popping."""
    rng = np.random.default_rng(1)
    bank = random_bank(rng, n=30)
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
                         ("detail_band", "low")):
        with pytest.raises(FacesynthError, match=f"model.{field}"):
            check_detail(dataclasses.replace(FaceModelConfig(), **{field: value}))


def test_the_talking_head_graph_carries_the_detail(shared_clip_dir, tmp_path):
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
    model = FaceModel.fit(seq, FaceModelConfig(detail=1.0), rows=rows, progress=False)
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
