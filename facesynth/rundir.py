"""The run directory that ``train.py`` writes and evaluation and export read::

    RUN/config.yaml         the composed Hydra config (data, split, seed, model, regressor)
    RUN/face_model/         the face model artifact (facesynth.model.artifact)
    RUN/sadm/               the SADM artifact: sadm.json + regressor.safetensors (facesynth.sadm.fit)
    RUN/eri/                an ERI run's model instead (facesynth.eri.model), with eri_metrics.json
    RUN/metrics.json        figures (facesynth.eval.sadm_eval), with config, versions, fingerprint
    RUN/report.md, RUN/plots/

This module is the one place that knows the layout as a whole: it reloads a run's data and
split from ``config.yaml`` and rebuilds its synthesizer. It sits below evaluation and export
(docs/architecture.md): the run's printed summary is :mod:`facesynth.eval.summary`'s.
"""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path

import numpy as np
import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from facesynth.data import FaceSequence, load_sequence, temporal_split
from facesynth.data.config import DataConf
from facesynth.data.readers import ingest_video
from facesynth.data.smoothing import FAST_RADII_S, LIGHT_SHIFT_PX, smooth_sequence, split_bounds
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.sadm.fit import SADM, SADMConfig, load_sadm, save_sadm
from facesynth.sadm.synthesis import Synthesizer

CONFIG = "config.yaml"
METRICS = "metrics.json"
REPORT = "report.md"
PLOTS = "plots"
ERI_DIR = "eri"
# data settings newer than some runs, with the value those runs had (a smoothed run without the
# threshold was smoothed at 0.35 face radii/s, one without the centroid's limit with no limit)
LEGACY_DATA = {"smooth_landmarks": False, "smooth_fast_radii_s": 0.35, "smooth_light_shift_px": None}


def check_data_config(data_cfg) -> None:
    """FacesynthError naming the ``data.*`` setting that cannot work, before anything is loaded."""
    if data_cfg.max_frames is not None and data_cfg.max_frames < 1:
        raise FacesynthError(f"data.max_frames must be >= 1 (or null: every frame), got {data_cfg.max_frames}")
    if not 0 < data_cfg.train_fraction < 1:
        raise FacesynthError(f"data.train_fraction must be in (0, 1), got {data_cfg.train_fraction}")
    if data_cfg.gap < 0:
        raise FacesynthError(f"data.gap must be >= 0, got {data_cfg.gap}")
    if not getattr(data_cfg, "smooth_fast_radii_s", FAST_RADII_S) > 0:
        raise FacesynthError(f"data.smooth_fast_radii_s must be > 0 (face radii per second), got {data_cfg.smooth_fast_radii_s}")
    shift = getattr(data_cfg, "smooth_light_shift_px", LIGHT_SHIFT_PX)
    if shift is not None and not shift > 0:
        raise FacesynthError(f"data.smooth_light_shift_px must be > 0 (frame px) or null (no limit), got {shift}")
    if data_cfg.kind == "synthetic" and data_cfg.n_frames < 2:
        raise FacesynthError(f"data.n_frames must be >= 2 (a training and a test frame), got {data_cfg.n_frames}")


def load_data(data_cfg, seed: int) -> FaceSequence:
    """The sequence a ``data`` config names (synthetic subject or a real folder/file)."""
    check_data_config(data_cfg)
    if data_cfg.kind == "synthetic":
        seq = make_synthetic_sequence(n_frames=data_cfg.n_frames, size=data_cfg.size, seed=seed)
    elif data_cfg.kind == "video":
        if not data_cfg.path:
            raise FacesynthError("data.path is required with data=video (a folder in the ingest layout)")
        seq = load_sequence(data_cfg.path)
    else:
        raise FacesynthError(f"data.kind must be 'synthetic' or 'video', got {data_cfg.kind!r}")
    if data_cfg.max_frames:
        seq = seq.subset(np.arange(min(len(seq), data_cfg.max_frames)))
    if data_cfg.kind == "video" and getattr(data_cfg, "smooth_landmarks", False):  # tracked: zero phase, per part
        seq = smooth_sequence(seq, split_bounds(len(seq), float(data_cfg.train_fraction), int(data_cfg.gap)),
                              fast_radii_s=float(getattr(data_cfg, "smooth_fast_radii_s", FAST_RADII_S)),
                              light_shift_px=getattr(data_cfg, "smooth_light_shift_px", LIGHT_SHIFT_PX))
    return seq


def read_config(run_dir: str | os.PathLike, hint: str = "not a train.py run directory"):
    """The run's ``config.yaml`` (an OmegaConf node); FacesynthError with ``hint`` when absent,
    and naming the file when it is not YAML, not a mapping, or lacks ``seed`` or one of the
    ``data`` settings (:class:`facesynth.data.config.DataConf`'s fields, which ``train.py``
    writes whole)."""
    path = Path(run_dir) / CONFIG
    if not path.is_file():
        raise FacesynthError(f"{path}: not found ({hint})")
    try:
        cfg = OmegaConf.load(path)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, OmegaConfBaseException) as exc:
        first = " ".join(str(exc).split())[:160]
        raise FacesynthError(f"{path}: not a readable YAML config ({type(exc).__name__}: {first})") from None
    if not isinstance(cfg, DictConfig):
        raise FacesynthError(f"{path}: expected a mapping of settings (train.py's config), got a {type(cfg).__name__}")
    if not isinstance(cfg.get("data"), DictConfig):
        raise FacesynthError(f"{path}: no 'data' settings (the run's data and split); not a train.py config?")
    for name, value in LEGACY_DATA.items():  # settings added since: a run without one was trained without it
        if name not in cfg.data:
            cfg.data[name] = value
    missing = [f"data.{f.name}" for f in fields(DataConf) if f.name not in cfg.data] + \
        (["seed"] if "seed" not in cfg else [])
    if missing:
        raise FacesynthError(f"{path}: missing {', '.join(missing)} (train.py writes every setting)")
    return cfg


def run_data(cfg) -> tuple[FaceSequence, np.ndarray, np.ndarray]:
    """The sequence and temporal split (train rows, test rows) of a run's config."""
    seq = load_data(cfg.data, int(cfg.seed))
    tr, te = temporal_split(len(seq), float(cfg.data.train_fraction), int(cfg.data.gap))
    return seq, tr, te


def training_landmarks(run_dir: str | os.PathLike) -> np.ndarray:
    """(N, 68, 2) training landmarks of a ``train.py`` run: its ``config.yaml`` names the data
    and the temporal split, which are reloaded (no frames are decoded)."""
    cfg = read_config(run_dir, "so the run's training landmarks are unknown; pass --landmarks L.npy "
                               "(the training landmarks) or --components 0 (no appearance compression)")
    seq, rows, _ = run_data(cfg)
    return np.asarray(seq.landmarks[rows], np.float32)


def input_files(run_dir: str | os.PathLike) -> list[Path]:
    """Every file a run's export reads or that belongs to the run: the run folder's own files
    and, as its ``config.yaml`` names them, its training data (an ingest folder's
    ``landmarks.npy``, ``meta.json`` and video, or a landmark file). An output written onto
    one of them would destroy the run (``io.refuse_overwriting_inputs``); a config that
    cannot be read names no data (its own error comes when the data is loaded)."""
    d = Path(run_dir)
    files = [p for p in d.rglob("*") if p.is_file()] if d.is_dir() else []
    try:
        cfg = read_config(d)
        data = Path(str(cfg.data.path)) if cfg.data.kind == "video" and cfg.data.path else None
    except FacesynthError:
        data = None
    if data is not None and data.is_dir():
        files += [data / "landmarks.npy", data / "meta.json"]
        try:
            video, _ = ingest_video(data)
        except FacesynthError:
            video = None
        files += [video] if video is not None else []
    elif data is not None:
        files.append(data)
    return files


def is_eri_run(run_dir: str | os.PathLike) -> bool:
    """True when ``run_dir`` holds an ERI model and no SADM."""
    d = Path(run_dir)
    return not (d / "sadm").is_dir() and ((d / "eri_model.json").is_file() or (d / ERI_DIR / "eri_model.json").is_file())


def load_synthesizer(run_dir: str | os.PathLike) -> tuple[Synthesizer, dict]:
    """Rebuild the :class:`Synthesizer` of a training run directory.

    Returns the synthesizer and metadata for the ONNX file (regressor, data fingerprint, run).
    """
    d = Path(run_dir)
    if not d.is_dir():
        raise FacesynthError(f"{d}: training run directory not found")
    sadm = load_sadm(d)
    return sadm.synthesizer(), {"regressor": sadm.name, "data_fingerprint": sadm.model.fingerprint, "run": d.name}


def save_run_synthesizer(run_dir: str | os.PathLike, model, regressor, features: str = "bs", clamp: bool = True) -> Path:
    """Write a face model and SADM regressor as a run directory (for tests and scripts
    that fit outside ``train.py``)."""
    sadm = SADM(model, regressor, regressor.name, SADMConfig(features=features, clamp_shape=clamp), regressor.config_dict())
    return save_sadm(sadm, run_dir)
