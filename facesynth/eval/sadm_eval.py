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
* ``psnr_frame_common``: as ``psnr_frame`` (same frames, same compositing) but over a
  region that does not depend on the landmark scheme: the hull of the clip's dlib points
  0-26 eroded 3 px (:mod:`facesynth.eval.common_region`), so ``ibug68`` and
  ``mediapipe478`` models compare; ``psnr_frame_common_regions``: {eyes, mouth_interior,
  rest, whole}: {row: {noise: dB}} inside it; ``psnr_frame_common_shares``: each region's
  share of the whole region's pixels (the frames evaluated), so that region figures combine
  into whole-region ones (:mod:`facesynth.eval.regions_gap`).
* ``sharpness_frame_common``: {region: {row: S}}: the rendered face's Sobel gradient energy
  over the real frame's in each common region, pasted with ``blend_face``, median over the
  frames evaluated, sigma 0 (:mod:`facesynth.eval.sharpness`; 1 = as detailed as the real
  frame).
* ``lpips_frame_common``: {face, eyes, mouth: {row: LPIPS}}: the perceptual distance
  (LPIPS-Alex, :mod:`facesynth.eval.perceptual`; lower is closer) of each region's square crop
  of the face pasted as for ``psnr_frame_common`` against the real frame's, median over the
  frames evaluated, sigma 0, rows ``sadm``, ``oracle`` and ``rewarp``
  (:func:`facesynth.eval.frame_level.frame_level`); left out without the ``perceptual`` extra.
* ``flicker_frame_common``: the face's mean absolute frame-to-frame change over consecutive
  held-out frames, rendered over real (rows ``sadm`` and ``rewarp``) and real, and the ratio
  to the real frames' (:mod:`facesynth.eval.flicker`).
* ``psnr_ref_regions``: {part: {row: {noise: dB}}}: ``psnr_ref`` per face part of the
  reference frame, each test frame's (:func:`facesynth.sadm.regions.frame_regions`: a closed
  mouth's interior counts as lips), rows ``sadm`` and
  ``mean_texture``; ``region_shrink``: the SADM's per-part weights towards the mean texture
  and their validation-slice figures (None: no shrinkage).
* ``ncc``: per-component normalised cross-correlation of predicted vs true b_g on the
  test frames at sigma 0 (the paper's Table 1).
* ``reference_stretch``: {median, p99, max} over the test frames of the largest area ratio of
  a reference triangle on the frame (:meth:`FaceModel.stretch`): where the reference frame
  holds too few pixels for a part, the render stretches them into streaks.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from facesynth import progress
from facesynth.data.sequence import FaceSequence
from facesynth.eval.flicker import flicker, flicker_rows
from facesynth.eval.frame_level import frame_level
from facesynth.eval.strip import strip_rows, strip_tiles
from facesynth.landmarks import get_scheme
from facesynth.metrics import ncc, psnr
from facesynth.sadm.fit import SADM
from facesynth.sadm.regions import frame_regions, masked_psnr01, pixel_errors


@dataclass
class EvalConfig:
    """noise: landmark noise levels (frame px). max_test_frames: the frame-level PSNR is
    measured on this many evenly spaced test frames (None or 0: every test frame); 100 keeps
    every row within 0.1 dB of the all-frames figures on a real clip (60 did not: docs/eval.md).
    feather: paste edge width; batch_size: frames per batched prediction/render.
    common_region: also measure ``psnr_frame_common`` (needs the clip's dlib landmarks);
    common_landmarks: where they are (a (T, 68, 2) .npy or clip folder indexed by video
    frame; None: found as :func:`facesynth.eval.common_region.common_landmarks` says).
    talking_head: also drive the avatar with its own held-out frames through the whole talking
    head (static / warp / full; :mod:`facesynth.eval.talking_head`; clips with frames, on up
    to ``talking_head_frames`` frames). flicker_frames: consecutive held-out frames of the
    flicker measure (with the common region; 0: not measured)."""

    noise: list = field(default_factory=lambda: [0.0, 1.0, 2.0, 3.0])
    frame_level: bool = True
    train_level: bool = True
    max_test_frames: int | None = 100
    feather: float = 2.0
    batch_size: int = 32
    common_region: bool = True
    common_landmarks: Optional[str] = None
    talking_head: bool = True
    talking_head_frames: int = 40
    flicker_frames: int = 40


def _key(s: float) -> str:
    return str(int(s)) if float(s).is_integer() else str(s)


def noisy_landmarks(lm: np.ndarray, sigma: float, seed: int, base_points: int | None = None) -> np.ndarray:
    """(N, P, 2) landmarks plus seeded Gaussian noise of ``sigma`` px (the evaluation's noise; sigma 0: unchanged).

    ``base_points``: the first this many points get the draws they would get alone (the
    face model's points: an ``ibug68+iris`` run sees the noise of the ``ibug68`` run on
    points 0-67); the others get draws of their own."""
    if sigma == 0:
        return lm
    nb = lm.shape[-2] if base_points is None else base_points
    rng = np.random.default_rng([seed, int(round(sigma * 1000))])
    out = lm.astype(np.float64)
    out[..., :nb, :] += rng.normal(0, sigma, lm[..., :nb, :].shape)
    if lm.shape[-2] > nb:
        out[..., nb:, :] += np.random.default_rng([seed, int(round(sigma * 1000)), 1]).normal(0, sigma, lm[..., nb:, :].shape)
    return out.astype(np.float32)


def _predict(syn, lm: np.ndarray, bs: int) -> np.ndarray:
    """(N, 68, 2) landmarks -> (N, C * M) predicted textures, in batches of ``bs``."""
    out = []
    with torch.no_grad():
        for s in range(0, len(lm), bs):
            t = syn.texture(torch.from_numpy(lm[s : s + bs]))
            out.append(t.reshape(len(t), -1).numpy())
    return np.concatenate(out)


def _quantiles(x: np.ndarray) -> dict:
    return {"median": float(np.median(x)), "p99": float(np.percentile(x, 99)), "max": float(np.max(x))}


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
    common: np.ndarray | None = None,
) -> tuple[dict, dict]:
    """Evaluate on ``test_rows`` (and ``train_rows``).

    ``common``: (len(seq), 68, 2) dlib landmarks of every row for ``psnr_frame_common``
    (:func:`facesynth.eval.common_region.common_landmarks`); None: not measured.

    Returns
    -------
    metrics : dict
        The ``metrics.json`` content (keys as documented in the module docstring).
    extras : dict
        Arrays for plots: ``err_map`` (H, W) mean squared error per reference pixel at
        sigma 0; ``per_frame``: ``frame`` (N_test,) frame rows, ``psnr_ref`` (N_test,) dB
        at sigma 0, and for the frame level ``frame_index`` (n,) positions evaluated and
        ``psnr_frame`` {row: (n,) dB}, with ``common`` ``psnr_frame_common`` {row: (n,) dB}
        and, with LPIPS, ``lpips_frame_common`` {region: {row: (n,)}}; ``grid`` list of dicts (``real``, ``synth`` uint8
        crops, ``frame`` row, ``psnr`` dB) for evenly spaced frame-level test frames; ``strip``:
        consecutive held-out frames, real and rendered (:mod:`facesynth.eval.strip`).
    """
    cfg = config or EvalConfig()
    model = sadm.model
    syn = sadm.synthesizer()
    n_model = syn.model_points
    noisy = functools.partial(noisy_landmarks, base_points=n_model)
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)  # what the face model samples
    test_rows = np.asarray(test_rows)
    lm_te = seq.landmarks[test_rows]
    tex_te = model.sample_textures(model_seq, test_rows, progress=True) if test_textures is None else test_textures
    b_true = model.appearance_params(tex_te)
    oracle = np.clip(model.texture_from_params(b_true), 0, 1)
    mean_tex = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), tex_te.shape)
    keys = [_key(s) for s in cfg.noise]
    psnr_ref = {"sadm": {}, "mean_texture": {}, "oracle": {}}
    pred0 = None
    mean_db, oracle_db = _psnr01(mean_tex, tex_te), _psnr01(oracle, tex_te)  # landmark noise does not change them
    parts = frame_regions(model, lm_te)  # per test frame: a closed mouth's interior is lips
    c = model.n_channels
    err = pixel_errors(mean_tex, tex_te, c)
    ref_regions = {name: {"sadm": {}, "mean_texture": dict.fromkeys(keys, masked_psnr01(err, m, c))} for name, m in parts.items()}
    for s, k in zip(cfg.noise, keys, strict=True):
        pred = _predict(syn, noisy(lm_te, s, seed), cfg.batch_size)
        pred0 = pred if s == 0 else pred0
        psnr_ref["sadm"][k] = _psnr01(pred, tex_te)
        err = pixel_errors(pred, tex_te, c)
        for name, m in parts.items():
            ref_regions[name]["sadm"][k] = masked_psnr01(err, m, c)
        psnr_ref["mean_texture"][k] = mean_db
        psnr_ref["oracle"][k] = oracle_db
    if pred0 is None:
        pred0 = _predict(syn, lm_te, cfg.batch_size)
    metrics = {
        "regressor": sadm.name,
        "n_shape": model.shape_pca.n_components,
        "n_appearance": model.appearance_pca.n_components,
        "train_frames": int(len(train_rows)),
        "test_frames": int(len(test_rows)),
        "features": sadm.config.features,
        "landmark_scheme": sadm.scheme,
        "gaze": sadm.gaze_summary(),
        "psnr_ref": psnr_ref,
        "psnr_ref_regions": ref_regions,
        "region_shrink": sadm.region_shrink,
        "ncc": [float(v) for v in ncc(sadm.predict_params(lm_te), b_true)],
        "reference_stretch": _quantiles(model.stretch(model_seq.landmarks[test_rows])),
    }
    err = ((np.clip(pred0, 0, 1) - tex_te) ** 2).reshape(len(tex_te), model.n_channels, -1).mean((0, 1))
    extras = {"err_map": model.sampler().to_image(torch.from_numpy(err)[None, None].float())[0, 0].numpy() * 255**2}
    sq0 = ((np.clip(pred0, 0, 1) - np.clip(tex_te, 0, 1)) * 255.0) ** 2
    extras["per_frame"] = {"frame": seq.frame_index[test_rows],
                           "psnr_ref": 10 * np.log10(255.0**2 / np.maximum(sq0.mean(1), 1e-12))}
    if cfg.train_level:
        train_rows = np.asarray(train_rows)
        tex_tr = model.sample_textures(model_seq, train_rows) if train_textures is None else train_textures
        mean_tr = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), tex_tr.shape)
        oracle_tr = np.clip(model.texture_from_params(model.appearance_params(tex_tr)), 0, 1)
        metrics["psnr_train_ref"] = {
            "sadm": {k: _psnr01(_predict(syn, noisy(seq.landmarks[train_rows], s, seed + 1), cfg.batch_size), tex_tr)
                     for s, k in zip(cfg.noise, keys, strict=True)},
            "mean_texture": dict.fromkeys(keys, _psnr01(mean_tr, tex_tr)),
            "oracle": dict.fromkeys(keys, _psnr01(oracle_tr, tex_tr)),
        }
    if cfg.frame_level and seq.has_frames:
        with progress.stage("frame-level PSNR") as st:
            pooled, per_frame, extras["grid"] = frame_level(
                model, lambda lm: _predict(syn, lm, cfg.batch_size), seq, test_rows, tex_te, oracle, cfg, seed, keys,
                noisy, common=None if common is None else common[test_rows])
            n = len(per_frame["index"])
            st.set(f"{n} of {len(test_rows)} test frames x {len(keys)} noise levels")
        common_pooled = pooled.pop("common", None)
        shares = pooled.pop("common_shares", None)
        sharp = pooled.pop("sharpness", None)
        lp = pooled.pop("lpips", None)
        metrics["psnr_frame"] = pooled
        if common_pooled is not None:
            metrics["psnr_frame_common"] = common_pooled["whole"]
            metrics["psnr_frame_common_regions"] = common_pooled
            metrics["psnr_frame_common_shares"] = shares
            metrics["sharpness_frame_common"] = sharp
            if lp is not None:
                metrics["lpips_frame_common"] = lp
            if cfg.flicker_frames > 1 and len(test_rows) > 1:
                pos = flicker_rows(len(test_rows), cfg.flicker_frames)
                fr = test_rows[pos]
                metrics["flicker_frame_common"] = flicker(
                    model, {"sadm": _predict(syn, seq.landmarks[fr], cfg.batch_size), "rewarp": tex_te[pos]}, seq, fr,
                    common[fr], cfg.feather)
        metrics["frame_level_frames"] = {"evaluated": n, "test_frames": int(len(test_rows)),
                                         "max_test_frames": cfg.max_test_frames, "spacing": "evenly spaced"}
        extras["per_frame"].update(frame_index=per_frame["index"], psnr_frame=per_frame["psnr"])
        if "psnr_common" in per_frame:
            extras["per_frame"]["psnr_frame_common"] = per_frame["psnr_common"]
        if "lpips" in per_frame:
            extras["per_frame"]["lpips_frame_common"] = per_frame["lpips"]
        extras["strip"] = strip_tiles(syn, seq, test_rows[strip_rows(len(test_rows))])
    return metrics, extras

