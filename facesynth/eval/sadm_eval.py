"""Evaluation of a fitted SADM: what ``metrics.json`` holds.

* ``psnr_ref``: PSNR (peak 255) of predicted vs true test textures in the reference
  frame over the mask, at landmark noise sigma (frame pixels) on the test landmarks;
  the target is always the clean frame's texture. Isolates appearance prediction.
* ``psnr_frame``: the whole pipeline: render at the noisy landmarks, paste into the
  original frame (feathered), PSNR over the face region of the clean landmarks.
* ``psnr_train_ref``: ``psnr_ref`` on the training frames (the paper's Table 2 setting).
* rows ``mean_texture`` (no SADM), ``oracle`` (the true texture projected on the
  appearance PCA) and, at frame level, ``rewarp`` (the frame's own texture re-warped:
  resampling loss alone).
* ``ncc``: per-component normalised cross-correlation of predicted vs true b_g on the
  test frames at sigma 0 (the paper's Table 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from facesynth.data.sequence import FaceSequence
from facesynth.imaging import composite
from facesynth.metrics import ncc, psnr
from facesynth.sadm.fit import SADM


@dataclass
class EvalConfig:
    """noise: landmark noise levels (frame px); max_test_frames caps the frame-level
    evaluation (evenly spaced) to bound its time; feather: paste edge width."""

    noise: list = field(default_factory=lambda: [0.0, 1.0, 2.0, 3.0])
    frame_level: bool = True
    train_level: bool = True
    max_test_frames: int | None = None
    feather: float = 2.0
    batch_size: int = 32


def _key(s: float) -> str:
    return str(int(s)) if float(s).is_integer() else str(s)


def noisy_landmarks(lm: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """(N, 68, 2) landmarks plus seeded Gaussian noise of ``sigma`` px (the evaluation's noise; sigma 0: unchanged)."""
    if sigma == 0:
        return lm
    rng = np.random.default_rng([seed, int(round(sigma * 1000))])
    return (lm + rng.normal(0, sigma, lm.shape)).astype(np.float32)


def _predict(syn, lm: np.ndarray, bs: int) -> np.ndarray:
    out = []
    with torch.no_grad():
        for s in range(0, len(lm), bs):
            t = syn.texture(torch.from_numpy(lm[s : s + bs]))
            out.append(t.reshape(len(t), -1).numpy())
    return np.concatenate(out)


def _psnr01(a: np.ndarray, b: np.ndarray) -> float:
    return psnr(np.clip(a, 0, 1) * 255.0, np.clip(b, 0, 1) * 255.0)


def evaluate_sadm(
    sadm: SADM,
    seq: FaceSequence,
    train_rows: np.ndarray,
    test_rows: np.ndarray,
    config: EvalConfig | None = None,
    seed: int = 0,
    train_textures: np.ndarray | None = None,
    test_textures: np.ndarray | None = None,
) -> tuple[dict, dict]:
    """Evaluate on ``test_rows`` (and ``train_rows``).

    Returns
    -------
    metrics : dict
        The ``metrics.json`` content (keys as documented in the module docstring).
    extras : dict
        Arrays for plots: ``err_map`` (H, W) mean squared error per reference pixel at
        sigma 0, ``grid`` list of (real, synthesized) uint8 frame crops.
    """
    cfg = config or EvalConfig()
    model = sadm.model
    syn = sadm.synthesizer()
    test_rows = np.asarray(test_rows)
    lm_te = seq.landmarks[test_rows]
    tex_te = model.sample_textures(seq, test_rows) if test_textures is None else test_textures
    b_true = model.appearance_params(tex_te)
    oracle = np.clip(model.texture_from_params(b_true), 0, 1)
    mean_tex = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), tex_te.shape)
    keys = [_key(s) for s in cfg.noise]
    psnr_ref = {"sadm": {}, "mean_texture": {}, "oracle": {}}
    pred0 = None
    for s, k in zip(cfg.noise, keys, strict=True):
        pred = _predict(syn, noisy_landmarks(lm_te, s, seed), cfg.batch_size)
        pred0 = pred if s == 0 else pred0
        psnr_ref["sadm"][k] = _psnr01(pred, tex_te)
        psnr_ref["mean_texture"][k] = _psnr01(mean_tex, tex_te)
        psnr_ref["oracle"][k] = _psnr01(oracle, tex_te)
    if pred0 is None:
        pred0 = _predict(syn, lm_te, cfg.batch_size)
    metrics = {
        "regressor": sadm.name,
        "n_shape": model.shape_pca.n_components,
        "n_appearance": model.appearance_pca.n_components,
        "train_frames": int(len(train_rows)),
        "test_frames": int(len(test_rows)),
        "features": sadm.config.features,
        "psnr_ref": psnr_ref,
        "ncc": [float(v) for v in ncc(sadm.predict_params(lm_te), b_true)],
    }
    err = ((np.clip(pred0, 0, 1) - tex_te) ** 2).reshape(len(tex_te), model.n_channels, -1).mean((0, 1))
    extras = {"err_map": model.sampler().to_image(torch.from_numpy(err)[None, None].float())[0, 0].numpy() * 255**2}
    if cfg.train_level:
        train_rows = np.asarray(train_rows)
        tex_tr = model.sample_textures(seq, train_rows) if train_textures is None else train_textures
        mean_tr = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), tex_tr.shape)
        oracle_tr = np.clip(model.texture_from_params(model.appearance_params(tex_tr)), 0, 1)
        metrics["psnr_train_ref"] = {
            "sadm": {k: _psnr01(_predict(syn, noisy_landmarks(seq.landmarks[train_rows], s, seed + 1), cfg.batch_size), tex_tr)
                     for s, k in zip(cfg.noise, keys, strict=True)},
            "mean_texture": {k: _psnr01(mean_tr, tex_tr) for k in keys},
            "oracle": {k: _psnr01(oracle_tr, tex_tr) for k in keys},
        }
    if cfg.frame_level and seq.has_frames:
        metrics["psnr_frame"], extras["grid"] = _frame_level(sadm, syn, seq, test_rows, tex_te, oracle, cfg, seed, keys)
    return metrics, extras


def _frame_level(sadm, syn, seq, rows, tex_te, oracle, cfg, seed, keys):
    """Whole-pipeline PSNR in the original frames (pooled over frames)."""
    model = sadm.model
    pick = np.arange(len(rows))
    if cfg.max_test_frames and len(rows) > cfg.max_test_frames:
        pick = np.unique(np.linspace(0, len(rows) - 1, cfg.max_test_frames).round().astype(int))
    lm = seq.landmarks[rows[pick]]
    mean = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), (len(pick), tex_te.shape[1]))
    sources = {"sadm": None, "mean_texture": mean, "oracle": oracle[pick], "rewarp": tex_te[pick]}
    sq = {name: {k: [0.0, 0] for k in keys} for name in sources}
    grid = []
    show = set(np.linspace(0, len(pick) - 1, min(6, len(pick))).round().astype(int).tolist())
    clean_crop, clean_mask, clean_place = model.render(mean[:1].repeat(len(pick), 0), lm)
    for j, frame in enumerate(seq.iter_frames(rows[pick])):
        h, w = frame.shape[:2]
        region = cv2.warpAffine(clean_mask[j], clean_place[j], (w, h)) > 0.999
        region = cv2.erode(region.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        for s, k in zip(cfg.noise, keys, strict=True):
            lmn = noisy_landmarks(lm[j : j + 1], s, seed + 17 * j)
            texs = np.concatenate([_predict(syn, lmn, 1) if t is None else t[j : j + 1] for t in sources.values()])
            crops, masks, places = model.render(texs, np.repeat(lmn, len(texs), 0))
            for i, name in enumerate(sources):
                out = composite(crops[i], masks[i], places[i], frame, cfg.feather)
                d = (out.astype(np.float64) - frame)[region]
                sq[name][k][0] += float((d**2).sum())
                sq[name][k][1] += d.size
                if name == "sadm" and s == 0 and j in show:
                    ys, xs = np.nonzero(region)
                    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
                    grid.append((frame[y0:y1, x0:x1], out[y0:y1, x0:x1]))
    res = {name: {k: (10 * np.log10(255.0**2 / (v[0] / max(v[1], 1))) if v[0] > 0 else float("inf"))
                  for k, v in d_.items()} for name, d_ in sq.items()}
    return res, grid
