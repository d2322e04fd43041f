"""Fitting a shape-appearance dependence mapping (SADM) on a face model, and its artifact
(the run directory's part of it; the whole layout is :mod:`facesynth.runs.rundir`)::

    RUN/face_model/         the face model artifact (facesynth.model.artifact)
    RUN/sadm/sadm.json      regressor name + hyper-parameters, SADM settings, provenance
    RUN/sadm/regressor.safetensors

References
----------
The linear SADM (A = G S^T (S S^T)^-1) is Eq. 5 of the shape-appearance dependence paper
this project builds on; the other regressors replace that map.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from facesynth.artifact import manifest_field, read_manifest, read_tensors, rebuild, save_artifact
from facesynth.data.sequence import FaceSequence
from facesynth.errors import FacesynthError
from facesynth.model.artifact import load_face_model, save_face_model
from facesynth.model.artifact import read_manifest as face_model_manifest
from facesynth.model.face_model import FaceModel
from facesynth.regressors import REGISTRY, Regressor, search
from facesynth.sadm.compress import compress_synthesizer
from facesynth.sadm.synthesis import GlobalAppearance, ShapeEncoder, ShapeFeatures, Synthesizer

log = logging.getLogger(__name__)
SADM_FORMAT, SADM_FORMAT_VERSION = "facesynth.sadm", 1
SADM_TENSORS, SADM_MANIFEST = "regressor.safetensors", "sadm.json"


@dataclass
class SADMConfig:
    """How the mapping is trained (the Hydra ``sadm`` node).

    features : 'bs' (the paper), 'landmarks' (aligned coordinates), 'bs+landmarks', or
        'landmarks_rigid' (coordinates aligned on the eye corners and nose only)
    augment_sigma : std (frame pixels) of Gaussian noise added to copies of the
        training landmarks, targets unchanged: trains robustness to landmark noise;
        None = the regressor's own (``sadm_defaults``: 2 px, krr 1 px)
    augment_copies : number of noisy copies (0: no augmentation)
    search : grid-search the regressor's hyper-parameters on the validation slice
    val_fraction : the last fraction of the training segment used as validation
    clamp_shape : clamp b_s to +-k sqrt(lambda) before the regressor
    """

    features: str = "landmarks"
    augment_sigma: Optional[float] = None
    augment_copies: int = 4
    search: bool = False
    val_fraction: float = 0.15
    clamp_shape: bool = True


@dataclass
class SADM:
    """A fitted mapping: ``regressor`` maps shape features to b_g of ``model``."""

    model: FaceModel
    regressor: Regressor
    name: str
    config: SADMConfig
    regressor_config: dict = field(default_factory=dict)
    search_table: list = field(default_factory=list)

    def appearance(self) -> GlobalAppearance:
        return GlobalAppearance(self.model, self.regressor, self.config.features)

    def synthesizer(self) -> Synthesizer:
        """The whole landmarks -> face graph (eval mode)."""
        return Synthesizer(self.model, self.appearance(), self.config.clamp_shape).eval()

    def compressed(self, landmarks: np.ndarray, keep: int | None = None, predicted_variance: float | None = None):
        """The synthesizer with only the appearance components of largest predicted variance
        over ``landmarks`` (N, P, 2) (the training frames); the rest are folded into the
        mean. Returns ``(Synthesizer, info)``; see :func:`facesynth.sadm.compress.compress_synthesizer`."""
        return compress_synthesizer(self.synthesizer(), landmarks, keep, predicted_variance)

    def features(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) frame landmarks -> (N, F) regressor inputs."""
        return ShapeFeatures.numpy(self.model, landmarks, self.config.features, self.config.clamp_shape)

    def predict_params(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) -> predicted b_g (N, K_g), clamped."""
        app = self.appearance().eval()
        enc = ShapeEncoder(self.model, self.config.clamp_shape)
        with torch.no_grad():
            return app.params(*enc(torch.from_numpy(np.asarray(landmarks, np.float32)))).numpy()


def make_config(name: str, params: dict):
    """The config dataclass of regressor ``name`` filled with ``params`` (its defaults elsewhere)."""
    try:
        return REGISTRY[name].config_class(**params)
    except TypeError as exc:
        raise FacesynthError(f"regressor '{name}': bad hyper-parameters {params}: {exc}") from None


def resolve_sadm_config(name: str, config: SADMConfig | None = None) -> SADMConfig:
    """``config`` (default ``SADMConfig()``) with its None fields set from regressor
    ``name``'s ``sadm_defaults``; FacesynthError for an unknown regressor."""
    if name not in REGISTRY:
        raise FacesynthError(f"unknown regressor '{name}' (available: {', '.join(sorted(REGISTRY))})")
    cfg = config or SADMConfig()
    return replace(cfg, **{k: v for k, v in REGISTRY[name].sadm_defaults.items() if getattr(cfg, k) is None})


def fit_sadm(
    model: FaceModel,
    seq: FaceSequence,
    rows: np.ndarray,
    textures: np.ndarray,
    name: str,
    params: dict | None = None,
    config: SADMConfig | None = None,
    seed: int = 0,
) -> SADM:
    """Fit the mapping on training ``rows`` of ``seq``.

    Parameters
    ----------
    textures : (len(rows), C * M) float32 training textures (as from model.sample_textures)
    name, params : regressor name in the registry and its hyper-parameters
    config : SADM settings (default ``SADMConfig()``); fields left None take the regressor's
        ``sadm_defaults`` (krr: 1 px augmentation), as in ``train.py regressor=NAME``
    """
    cfg = resolve_sadm_config(name, config)
    params = dict(params or {})
    rows = np.asarray(rows)
    lm = seq.landmarks[rows]
    y = model.appearance_params(textures)

    def features(landmarks):
        return ShapeFeatures.numpy(model, landmarks, cfg.features, cfg.clamp_shape)

    n_val = int(round(len(rows) * cfg.val_fraction))
    fit_idx, val_idx = np.arange(len(rows) - n_val), np.arange(len(rows) - n_val, len(rows))
    rng = np.random.default_rng(seed)

    def design(idx):
        lms, ys = [lm[idx]], [y[idx]]
        for _ in range(cfg.augment_copies if cfg.augment_sigma > 0 else 0):
            lms.append(lm[idx] + rng.normal(0, cfg.augment_sigma, lm[idx].shape).astype(np.float32))
            ys.append(y[idx])
        return features(np.concatenate(lms)), np.concatenate(ys)

    table: list = []
    if cfg.search:
        if n_val < 2:
            raise FacesynthError("search needs a validation slice: raise sadm.val_fraction")
        x_fit, y_fit = design(fit_idx)
        best, table = search(name, x_fit, y_fit, features(lm[val_idx]), y[val_idx],
                             REGISTRY[name].search_grid, make_config(name, params), seed)
        params = {**params, **(asdict(best) if hasattr(best, "__dataclass_fields__") else dict(best))}
        log.info("search for %s picked %s", name, params)
    x, yy = design(np.arange(len(rows)))
    torch.manual_seed(seed)
    x_val = features(lm[val_idx]) if n_val else None
    reg = REGISTRY[name].fit(x, yy, make_config(name, params), x_val, y[val_idx] if n_val else None, seed=seed)
    return SADM(model, reg.eval(), name, cfg, reg.config_dict(), table)


def save_sadm(sadm: SADM, run_dir: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write the face model (``run_dir/face_model/``) and the mapping (``run_dir/sadm/``:
    ``sadm.json`` + ``regressor.safetensors``), atomic per file."""
    d = Path(run_dir)
    save_face_model(sadm.model, d / "face_model")
    tensors = {k: v.detach().contiguous().numpy() for k, v in sadm.regressor.state_dict().items()}
    save_artifact(d / "sadm", SADM_TENSORS, SADM_MANIFEST, tensors, {
        "regressor": sadm.name,
        "regressor_config": sadm.regressor_config,
        "regressor_summary": sadm.regressor.summary(),
        "sadm": asdict(sadm.config),
        "search_table": sadm.search_table,
        "data_fingerprint": sadm.model.fingerprint,
        "landmark_scheme": sadm.model.scheme,
        "face_model_sha256": face_model_manifest(d / "face_model")["tensors_sha256"],
        **(extra or {}),
    }, SADM_FORMAT, SADM_FORMAT_VERSION)
    return d


def load_sadm(run_dir: str | os.PathLike) -> SADM:
    """Load a run written by :func:`save_sadm` (or by ``train.py``).

    Every failure (missing, truncated, altered or non-finite files, invalid JSON, missing
    fields, tensors that do not fit the regressor or the face model) is a FacesynthError
    naming the file. The SADM manifest is written last and records the face model's
    tensors' SHA-256, so a face model from another save is refused.
    """
    d = Path(run_dir)
    if not (d / "sadm" / SADM_MANIFEST).is_file():
        raise FacesynthError(f"{d}: not a training run (sadm/{SADM_MANIFEST} missing)")
    meta = read_manifest(d / "sadm", SADM_MANIFEST, SADM_FORMAT, SADM_FORMAT_VERSION, "SADM")
    where = d / "sadm" / SADM_MANIFEST
    name = manifest_field(meta, "regressor", where)
    if not isinstance(name, str) or name not in REGISTRY:
        raise FacesynthError(f"{where}: regressor {name!r} is not available in this build")
    model = load_face_model(d / "face_model")
    paired = meta.get("face_model_sha256")
    if paired is not None and paired != face_model_manifest(d / "face_model").get("tensors_sha256"):
        raise FacesynthError(f"{d / 'face_model'}: not the face model this SADM was saved with "
                             f"(its SHA-256 differs from {where}'s 'face_model_sha256')")
    scheme = meta.get("landmark_scheme", "ibug68")  # runs saved before schemes were recorded are 68-point
    if scheme != model.scheme:
        raise FacesynthError(f"{where}: landmark scheme {scheme!r}, but the face model in {d / 'face_model'} "
                             f"has {model.scheme!r}")
    tensors = read_tensors(d / "sadm", SADM_TENSORS, meta, "SADM regressor")
    conf = manifest_field(meta, "regressor_config", where)
    sadm_conf = manifest_field(meta, "sadm", where)

    def build() -> SADM:
        reg = REGISTRY[name].from_state(conf, {k: torch.from_numpy(v) for k, v in tensors.items()})
        cfg = SADMConfig(**{k: v for k, v in dict(sadm_conf).items() if k in SADMConfig.__dataclass_fields__})
        sadm = SADM(model, reg.eval(), name, cfg, conf, meta.get("search_table", []))
        _smoke_test(sadm)
        return sadm

    return rebuild(d / "sadm" / SADM_TENSORS, f"SADM regressor {name!r}", build)


def _smoke_test(sadm: SADM) -> None:
    """One forward pass on the reference shape: tensors that do not fit the face model
    raise here (RuntimeError), not at first use; non-finite outputs raise ValueError."""
    lm = torch.from_numpy(np.ascontiguousarray(sadm.model.reference.points, np.float32)[None])
    with torch.no_grad():
        outs = sadm.synthesizer()(lm)
    for out in outs if isinstance(outs, (tuple, list)) else (outs,):
        if not torch.isfinite(out).all():
            raise ValueError("the synthesizer's output on the reference shape is not finite")
