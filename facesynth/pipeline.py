"""The training job behind ``train.py``: data -> face model -> SADM -> evaluation -> run dir.

A run directory holds the model artifacts (see :mod:`facesynth.sadm.fit`),
``metrics.json``, ``report.md``, ``plots/`` and ``config.yaml``; every file records the
config, package versions and the data fingerprint.
"""

from __future__ import annotations

import logging
import random
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from facesynth import __version__
from facesynth.data import FaceSequence, load_sequence, temporal_split
from facesynth.errors import FacesynthError
from facesynth.eval.report import write_plots, write_report
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.io import write_json, write_text
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.provenance import package_versions
from facesynth.sadm.fit import SADMConfig, fit_sadm, save_sadm

log = logging.getLogger(__name__)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def load_data(data_cfg, seed: int) -> FaceSequence:
    """The sequence a ``data`` config names (synthetic subject or a real folder/file)."""
    if data_cfg.kind == "synthetic":
        from facesynth.data.synthetic import make_synthetic_sequence

        seq = make_synthetic_sequence(n_frames=data_cfg.n_frames, size=data_cfg.size, seed=seed)
    elif data_cfg.kind == "video":
        if not data_cfg.path:
            raise FacesynthError("data.path is required with data=video (a folder in the ingest layout)")
        seq = load_sequence(data_cfg.path)
    else:
        raise FacesynthError(f"data.kind must be 'synthetic' or 'video', got {data_cfg.kind!r}")
    if data_cfg.max_frames:
        seq = seq.subset(np.arange(min(len(seq), data_cfg.max_frames)))
    return seq


def _dataclass_from(node, cls):
    d = OmegaConf.to_container(node, resolve=True) if not isinstance(node, dict) else node
    names = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in names})


def run_training(cfg, out_dir: str | Path) -> dict:
    """Train and evaluate one configuration; returns ``metrics`` (also written to disk)."""
    from facesynth.config import regressor_params

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(cfg.seed)
    t0 = time.perf_counter()
    seq = load_data(cfg.data, cfg.seed)
    tr, te = temporal_split(len(seq), cfg.data.train_fraction, cfg.data.gap)
    container = OmegaConf.to_container(cfg, resolve=True)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    if cfg.model.kind == "eri":
        from facesynth.eri.train import train_eri

        return train_eri(cfg.eri, seq, out, cfg.seed)  # the whole run config is in config.yaml
    if cfg.model.kind != "aam":
        raise FacesynthError(f"model.kind must be 'aam' or 'eri', got {cfg.model.kind!r}")
    model, tex_tr = FaceModel.fit_with_textures(seq, _dataclass_from(cfg.model, FaceModelConfig), rows=tr)
    t1 = time.perf_counter()
    name, params = regressor_params(cfg.regressor)
    sadm = fit_sadm(model, seq, tr, tex_tr, name, params, _dataclass_from(cfg.sadm, SADMConfig), cfg.seed)
    t2 = time.perf_counter()
    metrics, extras = evaluate_sadm(sadm, seq, tr, te, _dataclass_from(cfg.eval, EvalConfig), cfg.seed, train_textures=tex_tr)
    t3 = time.perf_counter()
    provenance = {
        "facesynth_version": __version__,
        "data": {"name": seq.name, "fingerprint": seq.fingerprint, "frames": len(seq)},
        "packages": package_versions(),
        "config": container,
    }
    save_sadm(sadm, out, extra=provenance)
    metrics.update({
        "timings_s": {"face_model": t1 - t0, "sadm_fit": t2 - t1, "evaluate": t3 - t2},
        "regressor_summary": sadm.regressor.summary(),
        **provenance,
    })
    write_json(out / "metrics.json", metrics)
    plots = write_plots(metrics, extras, out / "plots")
    write_report(metrics, out, plots, {"data": f"{seq.name} ({len(seq)} frames, fingerprint {seq.fingerprint})",
                                        "seed": cfg.seed, "features": sadm.config.features})
    return metrics


def summary_lines(metrics: dict) -> list[str]:
    """Short printable summary of a metrics dict."""
    lines = [f"regressor={metrics['regressor']} shape={metrics['n_shape']} appearance={metrics['n_appearance']} "
             f"train={metrics['train_frames']} test={metrics['test_frames']}"]
    for key in ("psnr_ref", "psnr_frame", "psnr_train_ref"):
        if key in metrics:
            for row, vals in metrics[key].items():
                lines.append(f"{key:15s} {row:13s} " + "  ".join(f"s{k}={v:6.2f}" for k, v in vals.items()))
    lines.append(f"ncc mean={np.mean(metrics['ncc']):.3f} (first 5: {', '.join(f'{v:.2f}' for v in metrics['ncc'][:5])})")
    return lines
