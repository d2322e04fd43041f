"""Ratio images, eigenERI PCA, the SVR driving model, saving/loading, synthesis, training
report and the transfer-expression command, on small synthetic data."""

import json
import sys

import cv2
import numpy as np
import pytest
import torch

from facesynth.cli import main
from facesynth.eri.config import EriConfig
from facesynth.eri.driving import VARIANTS, SVRBank, fit_variant
from facesynth.eri.faps import N_FAPS
from facesynth.eri.model import EriModel
from facesynth.eri.ratio import apply_ratio, gaussian_in_mask, ratio_images
from facesynth.eri.render import write_video
from facesynth.eri.synthesis import EriSynthesizer
from facesynth.eri.train import train_eri
from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.metrics import psnr
from facesynth.model.reference import ReferenceFrame
from facesynth.model.warp import ToReference
from tests._eri import CFG, _sequence
from tests._faces import face_template


def test_ratio_of_the_neutral_frame_is_one(seq, model):
    np.testing.assert_allclose(model.ratios_of(seq, [0]), 0.0, atol=1e-6)  # log R with sigma = 1
    plain = EriModel.fit(seq, np.arange(12), EriConfig(**{**CFG, "log": False, "sigma": 2.0}))
    np.testing.assert_allclose(plain.ratios_of(seq, [0]), 1.0, atol=1e-6)
    assert np.abs(model.ratios_of(seq, [5])).max() > 0.01


def test_ratio_definition_and_inverse(rng):
    ref = ReferenceFrame.from_mean_shape(face_template(), 48)
    s = ToReference(ref)
    tex = torch.from_numpy(rng.uniform(0, 1, (2, 3, s.n_pixels)).astype(np.float32))
    neu = torch.from_numpy(rng.uniform(0.2, 1, (3, s.n_pixels)).astype(np.float32))
    r = ratio_images(tex, neu, s, eps=0.02, clip=100.0, sigma=0.0, log=False)
    np.testing.assert_allclose(r.numpy(), ((tex + 0.02) / (neu + 0.02)).numpy(), rtol=1e-6)
    np.testing.assert_allclose(apply_ratio(r, neu, 0.02).numpy(), tex.numpy(), atol=1e-5)
    rc = ratio_images(tex, neu, s, eps=0.02, clip=1.5, sigma=0.0, log=True)
    assert rc.abs().max() <= np.log(1.5) + 1e-6


def test_gaussian_in_mask_matches_opencv_inside(rng):
    ref = ReferenceFrame.from_mean_shape(face_template(), 96)
    s = ToReference(ref)
    vals = torch.from_numpy(rng.uniform(0, 1, (1, 1, s.n_pixels)).astype(np.float32))
    sigma = 1.5
    out = s.to_image(gaussian_in_mask(vals, s, sigma))[0, 0].numpy()
    img = s.to_image(vals)[0, 0].numpy()
    k = 2 * int(np.ceil(3 * sigma)) + 1
    ref_img = cv2.GaussianBlur(img, (k, k), sigma, borderType=cv2.BORDER_CONSTANT)
    inner = cv2.erode(ref.mask().astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    assert inner.sum() > 1000
    np.testing.assert_allclose(out[inner], ref_img[inner], atol=1e-5)
    const = gaussian_in_mask(torch.full((1, 3, s.n_pixels), 0.7), s, sigma)
    np.testing.assert_allclose(const.numpy(), 0.7, atol=1e-6)  # normalised at the mask edge too


def test_eigeneri_keeps_requested_variance(seq):
    from sklearn.decomposition import PCA

    m = EriModel.fit(seq, np.arange(12), EriConfig(**{**CFG, "variance": 0.9}))
    assert m.pca.explained_variance_ratio >= 0.9
    assert m.pca.truncate(m.pca.n_components - 1).explained_variance_ratio < 0.9
    data = m.ratios_of(seq, np.arange(12)).reshape(12, -1)
    evr = np.cumsum(PCA().fit(data).explained_variance_ratio_)
    assert m.pca.n_components == int(np.searchsorted(evr, 0.9 - 1e-12) + 1)
    assert m.meta["neutral"]["row"] == 0 and m.meta["variance_kept"] >= 0.9


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_svr_bank_matches_sklearn(variant, rng):
    from sklearn.svm import SVR, NuSVR

    x = rng.normal(0, 3, (60, 5)) + 10
    y = np.stack([np.sin(x[:, 0]) + x[:, 1], x[:, 2] * 0.5, np.cos(x[:, 3])], 1) * [1, 20, 0.1]
    bank = SVRBank.fit(x, y, {"variant": variant, "C": 2.0, "epsilon": 0.05, "nu": 0.4, "gamma": "scale"})
    xt = rng.normal(0, 3, (7, 5)) + 10
    kind, kernel = VARIANTS[variant]
    z, zt = (x - x.mean(0)) / x.std(0), (xt - x.mean(0)) / x.std(0)
    for k in range(3):
        t = (y[:, k] - y[:, k].mean()) / y[:, k].std()
        common = dict(kernel=kernel, C=2.0, gamma=1 / 5)
        ref = SVR(epsilon=0.05, **common) if kind == "eps" else NuSVR(nu=0.4, **common)
        want = ref.fit(z, t).predict(zt) * y[:, k].std() + y[:, k].mean()
        np.testing.assert_allclose(bank.predict(xt)[:, k], want, rtol=1e-4, atol=1e-4 * y[:, k].std())


def test_grid_search_picks_from_the_grid(rng):
    x, y = rng.normal(size=(50, 4)), rng.normal(size=(50, 2))
    cfg = EriConfig(grid_search=True, C_grid=[0.5, 5.0], gamma_grid=[0.5, 2.0])
    bank, rep = fit_variant("eps_rbf", x[:40], y[:40], cfg, x[40:], y[40:])
    assert len(rep["grid"]) == 4 and rep["params"]["C"] in (0.5, 5.0) and rep["params"]["gamma"] in (0.5, 2.0)
    assert bank.predict(x).shape == (50, 2)


def test_save_load_round_trip(model, tmp_path):
    model.save(tmp_path / "run" / "eri")
    back = EriModel.load(tmp_path / "run")
    f = np.random.default_rng(1).normal(0, 50, (4, N_FAPS)).astype(np.float32)
    for v in VARIANTS:
        np.testing.assert_allclose(back.predict_coefficients(f, v), model.predict_coefficients(f, v), atol=1e-6)
    assert back.driver == model.driver and back.neutral_index == 0
    np.testing.assert_array_equal(back.reference.triangles, model.reference.triangles)
    (tmp_path / "bad").mkdir()
    with pytest.raises(FacesynthError, match="not an ERI model"):
        EriModel.load(tmp_path / "bad")


def test_synthesis_steps(seq, model):
    img, lm = seq.frame(0), seq.landmarks[0]
    syn = EriSynthesizer(model, img, lm)
    zero = np.zeros((2, N_FAPS), np.float32)
    out, mask = syn.render(zero, "geometry", feather=0)
    assert mask.sum() > 2000 and psnr(out, np.stack([img, img]), mask) > 35  # warping B to itself
    true = model.pca.project(model.ratios_of(seq, [5]).reshape(1, -1))
    b5 = syn.textures(zero[:1], "eri", coefficients=true)  # B = the model's neutral: reproduces frame 5's texture
    f5 = model.textures(seq.frame(5)[None], seq.landmarks[5:6])
    assert psnr(b5.numpy(), f5.numpy(), peak=1.0) > 30
    f = model.faps(seq.landmarks[8:11])
    eri, _ = syn.render(f, "eri")
    assert eri.shape == (3, *img.shape) and eri.dtype == np.uint8
    with pytest.raises(FacesynthError, match="mode"):
        syn.render(f, "bogus")


def test_config_errors():
    with pytest.raises(FacesynthError, match="unknown keys"):
        EriConfig.from_dict({"widht": 3})
    with pytest.raises(FacesynthError, match="driver"):
        EriConfig(driver="svm")
    assert EriConfig.from_dict({"C": 3.0}).C == 3.0


def test_hydra_group_matches_defaults():
    from omegaconf import OmegaConf

    from facesynth.runs.config import CONF_DIR

    node = OmegaConf.load(CONF_DIR / "eri" / "default.yaml")
    assert EriConfig.from_dict(node) == EriConfig()


def test_train_eri_writes_tables(tmp_path):
    seq = _sequence(16, 2)
    m = train_eri({**CFG, "compare": ["linear", "not_a_regressor"]}, seq, tmp_path, seed=0)
    saved = json.loads((tmp_path / "eri_metrics.json").read_text())
    assert set(saved["coefficients"]) == set(VARIANTS) | {"sadm_linear"}
    assert saved["synthesis"]["psnr_db"]["geometry"] == pytest.approx(m["synthesis"]["psnr_db"]["geometry"])
    md = (tmp_path / "eri_report.md").read_text()
    assert "| nu_rbf |" in md and "geometry-only" in md
    assert EriModel.load(tmp_path).pca.n_components == m["model"]["n_components"]


def test_transfer_expression_cli(seq, model, tmp_path, capsys, monkeypatch):
    model.save(tmp_path / "run" / "eri")
    cv2.imwrite(str(tmp_path / "b.png"), cv2.cvtColor(seq.frame(0), cv2.COLOR_RGB2BGR))
    np.save(tmp_path / "b.npy", seq.landmarks[:1])
    np.savez(tmp_path / "drv.npz", landmarks=seq.landmarks, frames=np.stack(list(seq.iter_frames())))
    args = ["transfer-expression", "--eri", str(tmp_path / "run"), "--target", str(tmp_path / "b.png"),
            "--target-landmarks", str(tmp_path / "b.npy"), "--driver", str(tmp_path / "drv.npz"),
            "--out", str(tmp_path / "o.mp4"), "--sheet", str(tmp_path / "s.png"), "--sheet-rows", "3", "--json"]
    assert main(args) == 0
    cap = cv2.VideoCapture(str(tmp_path / "o.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == len(seq)
    sheet = cv2.imread(str(tmp_path / "s.png"))
    assert sheet.shape == (28 + 3 * 256, 3 * 256, 3)
    summary = json.loads(capsys.readouterr().out.strip())
    assert summary["frames"] == len(seq) and summary["frame_warp"] is True
    assert main([*args, "--still-frame", "--out", str(tmp_path / "still.mp4")]) == 0
    assert json.loads(capsys.readouterr().out.strip())["frame_warp"] is False
    assert main(args[:3] + ["--target", str(tmp_path / "nope.png")] + args[5:]) == 2
    assert "no such target" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "dlib", None)  # import dlib -> ImportError
    from facesynth.eri.target import _detect

    with pytest.raises(MissingExtraError, match="ingest"):
        _detect(seq.frame(0), tmp_path / "b.png")


def test_transfer_composites_into_the_image_warped_with_the_face(seq, model):
    """With a background warp (transfer-expression's default) each frame is the face over B's
    image warped to that frame's landmarks: off the face, the warped image's own pixels, which
    follow the jaw as the mouth opens; at B's neutral the warp is the identity."""
    from facesynth.eri.faps import compute_faps
    from facesynth.retarget import Retargeter
    from facesynth.runtime.fullframe import FrameWarp

    image, lm = seq.frame(0), seq.landmarks[0]
    syn = EriSynthesizer(model, image, lm)
    warp = FrameWarp(image, syn.neutral)
    open_ = int(np.argmax(np.linalg.norm(seq.landmarks[:, 66] - seq.landmarks[:, 62], axis=1)))
    rows = [0, open_]
    faps = compute_faps(seq.landmarks[rows], seq.landmarks[0])
    pos = Retargeter(syn.neutral, seq.landmarks[0], head_motion=False)(seq.landmarks[rows])
    still = list(syn.iter_render(faps, "eri", positions=pos))
    warped = list(syn.iter_render(faps, "eri", positions=pos, background=warp))
    _, masks = syn.render(faps, "eri", positions=pos)
    np.testing.assert_allclose(warp(pos[0]).astype(int), image.astype(int), atol=1)  # the neutral: identity
    bg = warp(pos[1])
    off = ~cv2.dilate(masks[1].astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    assert np.array_equal(warped[1][off], bg[off])  # off the face: the warped image itself
    assert np.array_equal(still[1][off], image[off])
    assert np.abs(bg.astype(int) - image).max() > 10  # which moved with the jaw


def test_write_video_is_atomic(tmp_path):
    with pytest.raises(FacesynthError, match="no frames"):
        write_video(tmp_path / "v.mp4", iter([]), 25)
    assert not list(tmp_path.iterdir())


def test_confidence_and_brightening_cap():
    from facesynth.eri.ratio import edge_confidence, to_multiplier

    ref = ReferenceFrame.from_mean_shape(face_template(), 64)
    s = ToReference(ref)
    flat = edge_confidence(torch.full((3, s.n_pixels), 0.6), s, 0.03)
    inner = cv2.erode(ref.mask().astype(np.uint8), np.ones((5, 5), np.uint8)).reshape(-1)[s.mask_index.numpy()] > 0
    np.testing.assert_allclose(flat[torch.from_numpy(inner)].numpy(), 1.0, atol=1e-6)  # smooth skin: full confidence
    xs = (s.mask_index % ref.size[1]).float()
    step = (xs > xs.median()).float().mul(0.5).add(0.2).expand(3, -1)
    conf = edge_confidence(step, s, 0.03)
    at_edge = (xs - xs.median()).abs() < 1
    assert conf[at_edge & torch.from_numpy(inner)].max() < 0.1
    assert edge_confidence(step, s, 0.0).eq(1).all()
    r = to_multiplier(torch.log(torch.tensor([[[2.0, 0.5, 1.0]]])), True, 4.0, None, 1.15)
    np.testing.assert_allclose(r.numpy().ravel(), [1.15, 0.5, 1.0], rtol=1e-6)
    half = to_multiplier(torch.log(torch.tensor([[[4.0]]])), True, 8.0, torch.tensor([0.5]))
    assert float(half) == pytest.approx(2.0)
