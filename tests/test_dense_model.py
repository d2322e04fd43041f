"""The face model, SADM, export and runtime on the 478-point MediaPipe scheme (issue 14),
with 478-point landmarks made without MediaPipe (tests/_dense.py: the canonical mesh bent
onto the synthetic subject's 68 points), and scheme mismatches as clear errors."""

from __future__ import annotations

import json
from functools import lru_cache

import cv2
import numpy as np
import pytest
import torch
from _dense import dense_sequence

from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.landmarks import MEDIAPIPE478, folded_triangles
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.artifact import load_face_model, save_face_model
from facesynth.sadm.fit import fit_sadm, load_sadm, save_sadm

CFG = FaceModelConfig(reference_width=64, appearance_variance=0.95)


@lru_cache(maxsize=1)
def _data(mesh_dir):
    seq68 = make_synthetic_sequence(n_frames=48, size=160, seed=3)
    seq = dense_sequence(seq68, mesh_dir / "mediapipe_canonical_468_arrays.npz")
    model, tex = FaceModel.fit_with_textures(seq, CFG, progress=False)
    return seq68, seq, model, tex


@pytest.fixture(scope="module")
def dense(shared_mesh):
    return _data(shared_mesh)


def test_face_model_on_478_points_uses_the_fixed_triangulation(dense):
    _, seq, model, _ = dense
    assert model.scheme == "mediapipe478" and model.reference.points.shape == (478, 2)
    fixed = MEDIAPIPE478.triangulation()
    folded = folded_triangles(model.reference.points, fixed)
    assert folded.any()  # this synthetic mean folds a few (8): they are kept, turned, placed last
    n = int((~folded).sum())
    np.testing.assert_array_equal(model.reference.triangles[:n], fixed[~folded])
    assert {frozenset(t) for t in model.reference.triangles[n:].tolist()} == {frozenset(t) for t in fixed[folded].tolist()}
    assert model.meta["triangles_folded_on_mean"] == np.flatnonzero(folded).tolist()
    assert not folded_triangles(model.reference.points, model.reference.triangles).any()
    # so a frame where they unfold has no hole: every background pixel of every render reaches the border
    import cv2

    _, mask, _ = model.render(np.repeat(model.appearance_pca.mean[None], len(seq), 0), seq.landmarks)
    for m in (mask > 0).astype(np.uint8):
        bg = np.pad(1 - m, 1, constant_values=1)
        _, labels = cv2.connectedComponents(bg, connectivity=4)
        assert (labels[1:-1, 1:-1][m == 0] == labels[0, 0]).all()
    assert np.isin(model.reference.triangles, MEDIAPIPE478.region("irises")).sum() == 0  # irises are no vertices
    assert model.shape_pca.mean.shape == (956,)


def test_texture_sampling_matches_opencv_affine_per_triangle(dense):
    """Each reference pixel's source point is its triangle's affine map (OpenCV's
    getAffineTransform from the reference triangle to the frame triangle)."""
    _, seq, model, _ = dense
    lm = seq.landmarks[5].astype(np.float64)
    sampler = model.sampler()
    src = (sampler.weights.double() @ torch.from_numpy(lm)).numpy()  # (M, 2)
    tri_index, _ = model.reference.rasterise()
    flat = sampler.mask_index.numpy()
    h, w = model.reference.size
    ys, xs = np.divmod(flat, w)
    t_of = tri_index.reshape(-1)[flat]
    for t in np.unique(t_of)[::40]:
        tri = model.reference.triangles[t]
        a = cv2.getAffineTransform(model.reference.points[tri].astype(np.float32), lm[tri].astype(np.float32))
        sel = t_of == t
        want = np.stack([xs[sel], ys[sel], np.ones(sel.sum())], -1) @ a.T
        np.testing.assert_allclose(src[sel], want, atol=1e-3)


def test_face_model_artifact_records_and_checks_the_scheme(dense, tmp_path):
    _, seq, model, _ = dense
    save_face_model(model, tmp_path / "fm")
    manifest = json.loads((tmp_path / "fm" / "face_model.json").read_text())
    assert manifest["landmark_scheme"] == "mediapipe478"
    back = load_face_model(tmp_path / "fm")
    assert back.scheme == "mediapipe478"
    np.testing.assert_allclose(back.shape_params(seq.landmarks[:4]), model.shape_params(seq.landmarks[:4]), atol=1e-5)
    for scheme, match in (("ibug68", r"face model tensors do not fit together \(shape PCA"),
                          ("dlib5", r"landmark scheme 'dlib5', expected one of ibug68, .*mediapipe478")):
        manifest["landmark_scheme"] = scheme
        (tmp_path / "fm" / "face_model.json").write_text(json.dumps(manifest))
        with pytest.raises(FacesynthError, match=match):
            load_face_model(tmp_path / "fm")


def test_scheme_mismatch_between_model_and_landmarks_is_a_clear_error(dense):
    seq68, seq, model, _ = dense
    with pytest.raises(FacesynthError, match=r"landmarks must have shape \(N, 478, 2\) .*these look like ibug68 landmarks"):
        model.shape_params(seq68.landmarks[:2])
    model68 = FaceModel.fit(seq68, CFG, rows=np.arange(12), progress=False)
    assert model68.scheme == "ibug68"
    with pytest.raises(FacesynthError, match=r"these look like mediapipe478 landmarks: map them with .*to_ibug68"):
        model68.render(model68.appearance_pca.mean[None], seq.landmarks[:1])


@pytest.mark.parametrize("name", ["linear", "mlp"])
def test_478_point_model_trains_exports_and_matches_torch_in_onnx_runtime(dense, tmp_path, name):
    pytest.importorskip("onnx")
    from facesynth.onnx.synthesis import check_export, export_run, export_synthesizer
    from facesynth.runtime import Renderer

    seq68, seq, model, tex = dense
    rows = np.arange(len(seq))
    sadm = fit_sadm(model, seq, rows, tex, name, {"max_epochs": 20, "hidden": [32]} if name == "mlp" else {})
    save_sadm(sadm, tmp_path / "run")
    assert json.loads((tmp_path / "run" / "sadm" / "sadm.json").read_text())["landmark_scheme"] == "mediapipe478"
    syn = load_sadm(tmp_path / "run").synthesizer()
    path = export_synthesizer(syn, tmp_path / "m.onnx")
    r = Renderer(path)
    assert r.metadata["landmark_scheme"] == "mediapipe478" and r.metadata["n_landmarks"] == 478
    assert r.input_shape == (478, 2)
    lm = seq.landmarks[::9] + np.float32(0.3)
    assert check_export(syn, path, lm, tol=1e-4) <= 1e-4
    crops, masks, _ = r.render(lm)
    with torch.no_grad():
        t_crop, t_mask, _ = syn(torch.from_numpy(lm))
    assert np.abs(crops - t_crop.numpy()).max() <= 1e-4 and masks.sum() > 0.3 * masks.size
    # what `facesynth export` writes (compressed appearance, int8 basis) matches too
    path2, syn2, meta = export_run(tmp_path / "run", tmp_path / "default.onnx", components=4, landmarks=seq.landmarks)
    assert meta["appearance_basis"] == "int8" and meta["appearance_components"] == 4
    assert check_export(syn2, path2, lm, tol=1e-4) <= 1e-4
    with pytest.raises(FacesynthError, match=r"this model takes mediapipe478 landmarks \(478 points\), got ibug68 ones"):
        r.render(seq68.landmarks[:1])


def test_sadm_run_with_a_face_model_of_another_scheme_is_refused(dense, tmp_path):
    _, seq, model, tex = dense
    save_sadm(fit_sadm(model, seq, np.arange(len(seq)), tex, "linear"), tmp_path / "run")
    meta_path = tmp_path / "run" / "sadm" / "sadm.json"
    meta = json.loads(meta_path.read_text())
    meta["landmark_scheme"] = "ibug68"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(FacesynthError,
                       match=r"sadm\.json: landmark scheme 'ibug68' needs a face model in 'ibug68', but the one in .* has 'mediapipe478'"):
        load_sadm(tmp_path / "run")


def test_per_pixel_source_equals_the_table_lookup(dense, monkeypatch):
    """A dense mesh reads each pixel's affine map by a per-pixel gather; a sparse one from
    (triangle, column) tables: both give the same render (the same products)."""
    import facesynth.model.warp as wt

    _, seq, model, tex = dense
    target = torch.from_numpy(model.to_canvas(seq.landmarks[:3] + np.float32(0.7))[0])
    t = torch.from_numpy(tex[:3]).reshape(3, 3, -1)
    assert model.reference.n_triangles > wt.PER_PIXEL_TRIANGLES
    with torch.no_grad():
        img, mask = wt.ToTarget(model.reference, model.span)(t, target)
        monkeypatch.setattr(wt, "PER_PIXEL_TRIANGLES", 10**6)
        img_tab, mask_tab = wt.ToTarget(model.reference, model.span)(t, target)
    assert torch.equal(mask, mask_tab) and mask.sum() > 0
    assert (img - img_tab).abs().max() <= 1e-5


@pytest.mark.parametrize("name", ["poly2", "svr", "krr"])
def test_every_regressor_fits_on_956_landmark_inputs(dense, name):
    """The other regressors on the 478 aligned points (956 inputs, train.py's defaults): they
    fit, and the synthesizer renders finite faces at held-out-like landmarks."""
    from facesynth.runs.config import train_defaults

    _, seq, model, tex = dense
    rname, params, cfg = train_defaults(name)
    sadm = fit_sadm(model, seq, np.arange(len(seq)), tex, rname, params, cfg)
    gaze = 4 * cfg.gaze_copies if cfg.gaze_mode in ("inside", "both") else 0  # mediapipe478 has irises: gaze is on
    assert sadm.features(seq.landmarks[:2]).shape == (2, 956 + gaze)
    with torch.no_grad():
        crop, mask, _ = sadm.synthesizer()(torch.from_numpy(seq.landmarks[-3:] + np.float32(0.5)))
    assert torch.isfinite(crop).all() and mask.sum() > 0
    b = sadm.predict_params(seq.landmarks)
    assert np.corrcoef(b[:, 0], model.appearance_params(tex)[:, 0])[0, 1] > 0.5  # it learnt the first component


# ------------------------------------------------------------------ landmark denoising
def test_denoise_projects_on_the_training_shapes(dense, rng):
    from facesynth.model.denoise import ShapeDenoiser
    from facesynth.model.face_model import SCHEME_DEFAULTS

    _, seq, model, _ = dense
    variance = SCHEME_DEFAULTS["dense"]["denoise_variance"]
    pca = model.denoise_pca  # on by default for the dense scheme
    assert pca is not None and pca.explained_variance_ratio >= variance
    k, d = pca.n_components, pca.mean.shape[0]
    assert 1 <= k < d // 4 and model.describe()["n_denoise_components"] == k
    # the training shapes keep all but (1 - variance) of their spread (in the aligned frame)
    aligned, _ = model.align(seq.landmarks)
    back, _ = model.align(model.denoise(seq.landmarks))
    resid = ((back - aligned) ** 2).sum() / (len(aligned) - 1)
    assert resid <= (1 - variance) * pca.total_variance * 1.05
    # the torch module (the graph's) equals the numpy form
    once = model.denoise(seq.landmarks[:6])
    with torch.no_grad():
        got = ShapeDenoiser(pca)(torch.from_numpy(seq.landmarks[:6])).numpy()
    np.testing.assert_allclose(got, once, atol=2e-3)
    # of i.i.d. unit landmark noise (2P = 956 dimensions) it keeps about K + 4: the subspace's K
    # and the 4 of the similarity, re-estimated from the noisy points (first order)
    clean = np.repeat(seq.landmarks[:1], 400, 0)
    noisy = clean + rng.normal(0, 1.0, clean.shape).astype(np.float32)
    kept = ((model.denoise(noisy) - model.denoise(clean)) ** 2).sum((1, 2)).mean()
    assert k < kept < k + 8, (kept, k)


def test_synthesis_reads_the_denoised_landmarks(dense):
    # the graph (Synthesizer), the model's numpy render (the evaluation's) and the SADM's numpy
    # prediction agree: all read FaceModel.denoise's landmarks
    from facesynth.sadm.fit import SADMConfig

    _, seq, model, tex = dense
    # without gaze: its eye-texture correction is the graph's, not b_g's (predict_params); without
    # the parts' shrinkage, which the graph's basis holds and b_g does not
    sadm = fit_sadm(model, seq, np.arange(len(seq)), tex, "linear", None, SADMConfig(gaze=False, region_shrink=False))
    syn = sadm.synthesizer()
    lm = seq.landmarks[::11] + np.float32(0.4)
    with torch.no_grad():
        crop, mask, place = syn(torch.from_numpy(lm))
        pred = syn.texture(torch.from_numpy(lm)).reshape(len(lm), -1).numpy()
    np.testing.assert_allclose(pred, np.clip(model.texture_from_params(sadm.predict_params(lm)), 0, 1), atol=2e-3)
    crop2, mask2, place2 = model.render(pred, lm)
    assert np.mean(mask[:, 0].numpy() != mask2) < 1e-3
    both = (mask[:, 0].numpy() > 0) & (mask2 > 0)
    assert np.abs(crop.permute(0, 2, 3, 1).numpy() - crop2)[both].max() < 2e-3
    np.testing.assert_allclose(place.numpy(), place2, atol=1e-3)


def test_denoise_settings_and_artifact(dense, tmp_path):
    seq68, seq, model, _ = dense
    save_face_model(model, tmp_path / "fm")
    back = load_face_model(tmp_path / "fm")
    np.testing.assert_array_equal(back.denoise_pca.components, model.denoise_pca.components)
    np.testing.assert_array_equal(back.denoise(seq.landmarks[:3]), model.denoise(seq.landmarks[:3]))
    rows = np.arange(12)
    off = FaceModel.fit(seq, FaceModelConfig(reference_width=48, denoise_variance=1.0), rows=rows, progress=False)
    assert off.denoise_pca is None
    np.testing.assert_array_equal(off.denoise(seq.landmarks[:2]), seq.landmarks[:2])
    m68 = FaceModel.fit(seq68, FaceModelConfig(reference_width=48), rows=rows, progress=False)
    assert m68.denoise_pca is None  # off by default on the sparse scheme
    save_face_model(m68, tmp_path / "fm68")
    assert load_face_model(tmp_path / "fm68").denoise_pca is None
    on68 = FaceModel.fit(seq68, FaceModelConfig(reference_width=48, denoise_variance=0.99), rows=rows, progress=False)
    assert on68.denoise_pca is not None and on68.denoise_pca.mean.shape == (136,)
    with pytest.raises(FacesynthError, match=r"model\.denoise_variance must be a fraction in \(0, 1\] \(1 = off\), got 1\.5"):
        FaceModel.fit(seq68, FaceModelConfig(denoise_variance=1.5), rows=rows, progress=False)
    with pytest.raises(FacesynthError, match=r"model\.reference_mouth_quantile must lie in \[0, 1\] \(0 = off\), got -0\.1"):
        FaceModel.fit(seq68, FaceModelConfig(reference_mouth_quantile=-0.1), rows=rows, progress=False)
    with pytest.raises(FacesynthError, match=r"model\.denoise_free must be one of \['eyes', 'none'\], got 'mouth'"):
        FaceModel.fit(seq68, FaceModelConfig(denoise_free="mouth"), rows=rows, progress=False)


def test_denoise_can_leave_the_eyes_as_given(dense, rng):
    # denoise_free="eyes": the basis also spans every eye and iris coordinate, so those points
    # come back exactly (a driver's eyelids outside the training range stay); the rest is denoised
    _, seq, model, _ = dense
    free = FaceModel.fit(seq, FaceModelConfig(reference_width=48, denoise_free="eyes"), rows=np.arange(24), progress=False)
    eyes = np.concatenate([MEDIAPIPE478.region("eyes"), MEDIAPIPE478.region("irises")])
    k = free.denoise_pca.n_components
    np.testing.assert_allclose(free.denoise_pca.components @ free.denoise_pca.components.T, np.eye(k), atol=1e-5)
    noisy = seq.landmarks[30:34] + rng.normal(0, 1.0, seq.landmarks[30:34].shape).astype(np.float32)
    out = free.denoise(noisy)
    np.testing.assert_allclose(out[:, eyes], noisy[:, eyes], atol=1e-3)
    rest = np.setdiff1d(np.arange(478), eyes)
    assert np.abs(out[:, rest] - noisy[:, rest]).mean() > 0.3


def test_app_drives_a_478_point_model(dense, tmp_path, capsys):
    pytest.importorskip("onnx")
    from facesynth.cli import main
    from facesynth.onnx.synthesis import export_synthesizer

    seq68, seq, model, tex = dense
    path = export_synthesizer(fit_sadm(model, seq, np.arange(len(seq)), tex, "linear").synthesizer(), tmp_path / "m.onnx")
    np.save(tmp_path / "lm.npy", seq.landmarks[:5])
    np.save(tmp_path / "lm68.npy", seq68.landmarks[:5])
    out = tmp_path / "out.mp4"
    base = ["app", "--model", str(path), "--out", str(out), "--size", "160x160", "--no-progress"]
    assert main(base + ["--landmarks", str(tmp_path / "lm.npy"), "--save-landmarks", str(tmp_path / "saved.npy")]) == 0
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    cap.release()
    np.testing.assert_array_equal(np.load(tmp_path / "saved.npy"), seq.landmarks[:5])  # absolute motion: as given
    capsys.readouterr()
    out.unlink()
    assert main(base + ["--landmarks", str(tmp_path / "lm.npy"), "--motion", "relative"]) == 2  # no avatar metadata
    assert "no avatar_neutral in the metadata" in capsys.readouterr().err
    assert main(base + ["--landmarks", str(tmp_path / "lm68.npy")]) == 2  # 68 points cannot become 478
    assert "mediapipe478" in capsys.readouterr().err and not out.exists()


def test_retargeting_478_points_is_a_similarity_for_a_similar_face(dense):
    # closed form: an avatar whose neutral is the driver's under a similarity S (every FAP unit
    # scaled alike) receives S of each driver frame, head motion included; any scheme
    from facesynth.retarget import Retargeter, point_units

    _, seq, model, _ = dense
    lm = seq.landmarks.astype(np.float64)
    theta, k, t = 0.2, 1.7, np.array([40.0, -25.0])
    rot = k * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    r = Retargeter(lm[0] @ rot.T + t, lm[0], scheme="mediapipe478")
    np.testing.assert_allclose(r(lm[1:9]), lm[1:9] @ rot.T + t, atol=1e-3)
    units = point_units(MEDIAPIPE478, lm[0])
    assert units.shape == (478, 2) and (units >= 0).all()
    assert (units[MEDIAPIPE478.region("inner_lips")] == units[MEDIAPIPE478.region("outer_lips")][0]).all()
    with pytest.raises(FacesynthError, match=r"avatar neutral: expected finite \(478, 2\) landmarks"):
        Retargeter(lm[0, :68], lm[0], scheme="mediapipe478")
    with pytest.raises(FacesynthError, match=r"retargeting takes ibug68 or mediapipe478 landmarks, not 'ibug68\+iris'"):
        Retargeter(lm[0], lm[0], scheme="ibug68+iris")


def test_478_point_avatar_is_reenacted_from_its_metadata(dense, tmp_path):
    # an export with its avatar metadata drives in relative motion: self-driving from the
    # avatar's own neutral returns its own frames' shapes, projected on its shape space
    pytest.importorskip("onnx")
    from facesynth.onnx.avatar import avatar_metadata, shape_space
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.runtime import Reenactor

    _, seq, model, tex = dense
    syn = fit_sadm(model, seq, np.arange(len(seq)), tex, "linear").synthesizer()
    meta = avatar_metadata(syn, seq.landmarks, np.arange(len(seq)), seq)
    assert np.shape(meta["avatar_neutral"]) == (478, 2) and len(meta["shape_pca"]["mean"]) == 956
    path = export_synthesizer(syn, tmp_path / "avatar.onnx", meta)
    neutral = np.asarray(meta["avatar_neutral"], np.float32)
    re = Reenactor(path, driver_neutral=neutral)
    space = shape_space(syn, seq.landmarks)
    # each eye capped at the widest its training frames open it, on the 478-point eye contours
    from facesynth.landmarks import eye_openings, get_scheme

    widest = eye_openings(seq.landmarks, get_scheme("mediapipe478")).max(0)
    np.testing.assert_allclose(meta["shape_pca"]["eye_open_max"], widest, atol=1e-6)
    np.testing.assert_allclose(re._retarget.shape_space.eye_open_max, widest, atol=1e-6)
    # the part outside the components capped at the largest of the training frames'
    assert meta["shape_pca"]["residual_max"] == pytest.approx(shape_space(syn).norms(seq.landmarks)[0].max(), rel=1e-6)
    # and the components' parameters within the largest norm of theirs
    assert meta["shape_pca"]["param_norm_max"] == pytest.approx(shape_space(syn).norms(seq.landmarks)[1].max(), rel=1e-6)
    for i in (3, 17, 30):
        frame, got = re.step(seq.landmarks[i])
        np.testing.assert_allclose(got, space.project(seq.landmarks[i].astype(np.float64)), atol=2e-3)
        assert frame.shape == seq.frame(0).shape


def test_app_detects_478_points_on_a_driver_video(dense, shared_clip_dir, tmp_path):
    # --video with a 478-point model: MediaPipe's landmarks of the driver frames drive it as given
    pytest.importorskip("mediapipe")
    pytest.importorskip("onnx")
    import cv2

    from facesynth.cli import main
    from facesynth.data.detect_mediapipe import detect_landmarks_mediapipe
    from facesynth.onnx.synthesis import export_synthesizer

    _, seq, model, tex = dense
    path = export_synthesizer(fit_sadm(model, seq, np.arange(len(seq)), tex, "linear").synthesizer(), tmp_path / "m.onnx")
    video = shared_clip_dir("lp_d6") / "video.mp4"
    out, saved = tmp_path / "out.mp4", tmp_path / "lm.npy"
    assert main(["app", "--model", str(path), "--video", str(video), "--max-frames", "6", "--out", str(out),
                 "--save-landmarks", str(saved), "--no-progress"]) == 0
    cap = cv2.VideoCapture(str(video))
    frames = [cv2.cvtColor(cap.read()[1], cv2.COLOR_BGR2RGB) for _ in range(6)]
    cap.release()
    want = detect_landmarks_mediapipe(frames).landmarks
    got = np.load(saved)
    assert got.shape == (6, 478, 2) and np.isfinite(got).all()
    np.testing.assert_allclose(got, want, atol=1e-3)
