"""Structured configs for ``train.py`` (Hydra + OmegaConf): typos fail at start-up.

Groups: ``data`` (DataConf), ``model`` (ModelConf: the face model, and ``kind`` aam|eri),
``regressor`` (one schema per registered regressor, built from its config dataclass),
``sadm`` (SADMConfig), ``eval`` (EvalConfig).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from facesynth.eri.config import EriConfig
from facesynth.eval.sadm_eval import EvalConfig
from facesynth.model.face_model import FaceModelConfig
from facesynth.sadm.fit import SADMConfig, _make_config
from facesynth.sadm.regressors import REGISTRY


@dataclass
class DataConf:
    """kind: 'synthetic' (the embedded default subject) or 'video' (``path``: a folder in
    the ingest layout, a folder of images + .pts, or .npy/.npz). Temporal split:
    the first ``train_fraction`` trains, the rest (after ``gap`` frames) tests."""

    kind: str = "synthetic"
    path: Optional[str] = None
    n_frames: int = 240
    size: int = 256
    max_frames: Optional[int] = None
    train_fraction: float = 0.75
    gap: int = 0


@dataclass
class ModelConf(FaceModelConfig):
    """The face model (FaceModelConfig) plus ``kind``: 'aam' (SADM) or 'eri'."""

    kind: str = "aam"


@dataclass
class TrainConf:
    seed: int = 0
    data: DataConf = field(default_factory=DataConf)
    model: ModelConf = field(default_factory=ModelConf)
    regressor: Any = MISSING
    sadm: SADMConfig = field(default_factory=SADMConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    eri: EriConfig = field(default_factory=EriConfig)


def _omegaconf_type(tp):
    """tuple[...] -> List[...] (OmegaConf has no tuples)."""
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return typing.List[args[0] if args else Any]
    return tp


def regressor_schema(name: str) -> type:
    """A dataclass with ``name`` plus the fields of regressor ``name``'s config class."""
    cfg = _make_config(name, {})
    fields = [("name", str, field(default=name))]
    if dataclasses.is_dataclass(cfg):
        hints = typing.get_type_hints(type(cfg))
        for f in dataclasses.fields(cfg):
            default = getattr(cfg, f.name)
            if isinstance(default, (list, tuple, dict)):
                fields.append((f.name, _omegaconf_type(hints[f.name]), field(default_factory=lambda d=default: list(d) if isinstance(d, tuple) else d)))
            else:
                fields.append((f.name, hints[f.name], field(default=default)))
    return dataclasses.make_dataclass(f"{name.capitalize()}RegressorConf", fields)


def register_configs() -> None:
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConf)
    for name in REGISTRY:
        cs.store(group="regressor", name=f"{name}_schema", node=regressor_schema(name))


def regressor_params(node) -> tuple[str, dict]:
    """(name, hyper-parameters) from a ``regressor`` config node."""
    from omegaconf import OmegaConf

    d = OmegaConf.to_container(node, resolve=True) if not isinstance(node, dict) else dict(node)
    return d.pop("name"), d


def compose_config(overrides: list[str]):
    """The training config ``python train.py OVERRIDES`` runs with, composed by Hydra from
    the repository's ``conf/`` (without the ``hydra`` node). Bad overrides raise
    FacesynthError naming them."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from facesynth.errors import FacesynthError

    conf_dir = Path(__file__).resolve().parents[1] / "conf"
    if not (conf_dir / "config.yaml").is_file():
        raise FacesynthError(f"{conf_dir}: Hydra configs not found (composing a training config needs a source checkout)")
    register_configs()
    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            return compose(config_name="config", overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as exc:
        msg = " ".join(str(exc).split())
        raise FacesynthError(f"training config overrides {list(overrides)}: {msg}") from None


def train_defaults(regressor: str) -> tuple[str, dict, SADMConfig]:
    """What ``python train.py regressor=NAME`` trains with: the regressor's name and
    hyper-parameters and the SADM settings (a regressor's config may set some, e.g. krr's
    augmentation), composed by Hydra from the repository's ``conf/`` (for benchmarks and
    scripts that call :func:`facesynth.sadm.fit.fit_sadm` directly)."""
    from omegaconf import OmegaConf

    cfg = compose_config([f"regressor={regressor}"])
    name, params = regressor_params(cfg.regressor)
    return name, params, SADMConfig(**OmegaConf.to_container(cfg.sadm, resolve=True))
