"""The training job behind ``train.py``: data -> face model -> SADM -> evaluation -> run dir.

The run directory's layout is :mod:`facesynth.rundir`; every file records the config,
package versions and the data fingerprint.
"""

from __future__ import annotations

import logging
import random
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from facesynth import __version__, progress
from facesynth.data import FaceSequence, temporal_split
from facesynth.data.sequence import check_face_size
from facesynth.eri.train import train_eri
from facesynth.errors import FacesynthError
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.eri_report import write_eri_report
from facesynth.eval.report import write_plots, write_report
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.eval.talking_head import talking_head_figures
from facesynth.io import dumps_json, write_text
from facesynth.landmarks import get_scheme
from facesynth.model.face_model import FaceModelConfig
from facesynth.provenance import package_versions
from facesynth.rundir import CONFIG, METRICS, PLOTS, load_data
from facesynth.runs.config import dataclass_from, regressor_params
from facesynth.runs.width_guard import check_width_guard, guard_width
from facesynth.sadm.fit import SADMConfig, fit_sadm, save_sadm

log = logging.getLogger(__name__)
# below these, the evaluation's figures (PSNR over the test frames, NCC over time) say little
MIN_TRAIN_FRAMES, MIN_TEST_FRAMES = 20, 10


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def check_training_data(seq: FaceSequence, data_cfg) -> None:
    """FacesynthError naming the file when the data cannot train a model: no frames (the
    video it names is missing) or faces too small to be faces (landmarks not in pixels)."""
    src = Path(str(data_cfg.path)) if data_cfg.kind == "video" and data_cfg.path else None
    lm_file = src / "landmarks.npy" if src is not None and src.is_dir() else src
    if not seq.has_frames:
        missing = seq.meta.get("missing_video")
        raise FacesynthError(f"{missing}: video not found; training needs the frames of {lm_file}" if missing else
                             f"{lm_file or seq.name}: landmarks only, no frames to train on (give an ingest folder "
                             "with its video, a folder of images + .pts, or an .npz with frames)")
    check_face_size(seq.landmarks, str(lm_file or seq.name))


def run_training(cfg, out_dir: str | Path, on_fitted=None) -> dict:
    """Train and evaluate one configuration; returns ``metrics`` (also written to disk).
    ``on_fitted``: called once the SADM is saved in ``out_dir`` (face_model/, sadm/), before the
    evaluation and the report (the studio exports and drives the avatar meanwhile); the run folder
    is the same in the end."""
    check_width_guard(cfg.model.get("width_guard"))  # a bad setting fails before anything is written
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(cfg.seed)
    progress.set_quiet(bool(cfg.get("quiet", False)))
    t0 = time.perf_counter()
    seq = load_data(cfg.data, cfg.seed)
    check_training_data(seq, cfg.data)
    tr, te = temporal_split(len(seq), cfg.data.train_fraction, cfg.data.gap)
    if len(tr) < MIN_TRAIN_FRAMES or len(te) < MIN_TEST_FRAMES:
        log.warning("%s: only %d training and %d test frames (fewer than %d / %d): the evaluation's figures will "
                    "mean little", seq.name, len(tr), len(te), MIN_TRAIN_FRAMES, MIN_TEST_FRAMES)
    container = OmegaConf.to_container(cfg, resolve=True)
    write_text(out / CONFIG, OmegaConf.to_yaml(cfg, resolve=True))
    if cfg.model.kind == "eri":
        metrics = train_eri(cfg.eri, seq, out, cfg.seed, (tr, te))  # the whole run config is in config.yaml
        with progress.stage("report"):
            write_eri_report(metrics, out)
        return metrics
    if cfg.model.kind != "aam":
        raise FacesynthError(f"model.kind must be 'aam' or 'eri', got {cfg.model.kind!r}")
    eval_cfg = dataclass_from(cfg.eval, EvalConfig)
    # the common region's landmarks are found (or their absence reported) before any training
    common = (common_landmarks(seq, eval_cfg.common_landmarks)
              if eval_cfg.common_region and eval_cfg.frame_level and seq.has_frames else None)
    model_cfg = dataclass_from(cfg.model, FaceModelConfig)
    name, params = regressor_params(cfg.regressor)
    sadm_cfg = dataclass_from(cfg.sadm, SADMConfig)
    with progress.stage("face model") as st:  # on the scheme's base points (ibug68+iris: the 68 dlib points)
        model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
        guard_common = common
        if model_cfg.width_guard is not None and common is None and seq.has_frames:
            guard_common = common_landmarks(seq, eval_cfg.common_landmarks)
        model, tex_tr, width_report = guard_width(seq, model_seq, tr, model_cfg, name, params, sadm_cfg, guard_common,
                                                  eval_cfg.feather, cfg.seed)
        st.set(f"{len(tr)} training frames, {model.shape_pca.n_components} shape / "
               f"{model.appearance_pca.n_components} appearance components")
    if float(np.ptp(tex_tr)) < 0.5 / 255:  # below half a grey level: float rounding of one colour
        raise FacesynthError(f"{seq.name}: the training frames have the same colour everywhere on the face "
                             "(a plain-colour video?): there is no appearance to learn")
    t1 = time.perf_counter()
    with progress.stage(f"SADM fit ({name})"):
        sadm = fit_sadm(model, seq, tr, tex_tr, name, params, sadm_cfg, cfg.seed)
    t2 = time.perf_counter()
    provenance = {
        "facesynth_version": __version__,
        "data": {"name": seq.name, "fingerprint": seq.fingerprint, "frames": len(seq),
                 "landmark_smoothing": seq.meta.get("landmark_smoothing")},  # the filter, when data.smooth_landmarks
        "packages": package_versions(),
        "config": container,
    }
    if on_fitted is not None:
        save_sadm(sadm, out, extra=provenance)
        on_fitted()
    with progress.stage("evaluation"):
        metrics, extras = evaluate_sadm(sadm, seq, tr, te, eval_cfg, cfg.seed, train_textures=tex_tr, common=common)
    if eval_cfg.talking_head and seq.has_frames:
        with progress.stage("talking head (self-driven, held out)"):
            figures, extras["talking_head_strip"] = talking_head_figures(sadm.synthesizer(), seq, tr, te,
                                                                         eval_cfg.talking_head_frames)
        if figures:
            metrics["talking_head"] = figures
    t3 = time.perf_counter()
    metrics.update({
        "timings_s": {"face_model": t1 - t0, "sadm_fit": t2 - t1, "evaluate": t3 - t2},
        "regressor_summary": sadm.regressor.summary(),
        **({"width_guard": width_report} if width_report is not None else {}),
        **provenance,
    })
    try:  # a figure that is not valid JSON fails here, before any artifact is written
        text = dumps_json(metrics)
    except FacesynthError as exc:
        raise FacesynthError(f"{out / METRICS}: {exc}") from None
    if on_fitted is None:
        save_sadm(sadm, out, extra=provenance)  # face_model/ then sadm/ (its manifest, written last, pairs them)
    write_text(out / METRICS, text)
    with progress.stage("report"):
        plots = write_plots(metrics, extras, out / PLOTS)
        write_report(metrics, out, plots, {"data": f"{seq.name} ({len(seq)} frames, fingerprint {seq.fingerprint})",
                                            "seed": cfg.seed, "features": sadm.config.features},
                     worst_frames=extras.get("worst_frames"))
    return metrics
