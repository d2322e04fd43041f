"""Structured configs for ``facesynth train`` / ``train.py`` (Hydra + OmegaConf): typos fail at start-up.

Groups: ``data`` (DataConf), ``model`` (ModelConf: the face model, and ``kind`` aam|eri),
``regressor`` (one schema per registered regressor, built from its config dataclass),
``sadm`` (SADMConfig), ``eval`` (EvalConfig), ``eri`` (EriConfig).

Every default lives in a dataclass (here or in the stage that uses it); the yaml files
under ``facesynth/conf/`` (package data: an installed wheel trains too) only select a group
option or override a value (``experiment/``: a named study's overrides). A regressor's SADM
settings (e.g. krr's 1 px augmentation) come from its class (``sadm_defaults``) through
the ``sadm_default`` resolver, so that the composed config shows them.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import II, MISSING, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from facesynth.data.config import DataConf
from facesynth.eri.config import EriConfig
from facesynth.errors import FacesynthError
from facesynth.eval.sadm_eval import EvalConfig
from facesynth.model.face_model import FaceModelConfig
from facesynth.regressors import REGISTRY
from facesynth.sadm.fit import SADMConfig, make_config, resolve_sadm_config

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # the Hydra configs, shipped inside the package


@dataclass
class ModelConf(FaceModelConfig):
    """The face model (FaceModelConfig) plus ``kind``: 'aam' (SADM) or 'eri'."""

    kind: str = "aam"


@dataclass
class SADMConf(SADMConfig):
    """SADMConfig whose regressor-dependent fields default to the chosen regressor's
    ``sadm_defaults`` (resolved when the config is read)."""

    augment_sigma: Optional[float] = II("sadm_default:${regressor.name},augment_sigma")


@dataclass
class TrainConf:
    """seed: every random choice of the run; quiet: no progress bars or stage lines."""

    seed: int = 0
    quiet: bool = False
    data: DataConf = field(default_factory=DataConf)
    model: ModelConf = field(default_factory=ModelConf)
    regressor: Any = MISSING
    sadm: SADMConf = field(default_factory=SADMConf)
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
    cfg = make_config(name, {})
    fields = [("name", str, field(default=name))]
    if dataclasses.is_dataclass(cfg):
        hints = typing.get_type_hints(type(cfg))
        for f in dataclasses.fields(cfg):
            default = getattr(cfg, f.name)
            if isinstance(default, (list, tuple, dict)):
                factory = field(default_factory=lambda d=default: list(d) if isinstance(d, tuple) else d)
                fields.append((f.name, _omegaconf_type(hints[f.name]), factory))
            else:
                fields.append((f.name, hints[f.name], field(default=default)))
    return dataclasses.make_dataclass(f"{name.capitalize()}RegressorConf", fields)


def _sadm_default(regressor: str, key: str):
    return REGISTRY[regressor].sadm_defaults.get(key) if regressor in REGISTRY else None


def run_tag(model: str, regressor: str) -> str:
    """What a run trained, for its folder name: ``eri`` for ERI runs, else the regressor."""
    return "eri" if model == "eri" else regressor


def register_configs() -> None:
    """Register the schemas with Hydra's ConfigStore and the ``sadm_default`` / ``run_tag`` resolvers."""
    if not OmegaConf.has_resolver("sadm_default"):
        OmegaConf.register_new_resolver("sadm_default", _sadm_default)
    if not OmegaConf.has_resolver("run_tag"):
        OmegaConf.register_new_resolver("run_tag", run_tag)
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConf)
    for name in REGISTRY:
        # a group of their own: the ``regressor`` group lists only the yaml options (conf/regressor/NAME.yaml
        # extends ``/regressor_schema/NAME``)
        cs.store(group="regressor_schema", name=name, node=regressor_schema(name))


def dataclass_from(node, cls):
    """An instance of the config dataclass ``cls`` from a config node (or dict) holding its
    fields, among others (a ``model`` or ``sadm`` node of the training config)."""
    d = OmegaConf.to_container(node, resolve=True) if not isinstance(node, dict) else node
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in names})


def regressor_params(node) -> tuple[str, dict]:
    """(name, hyper-parameters) from a ``regressor`` config node."""
    d = OmegaConf.to_container(node, resolve=True) if not isinstance(node, dict) else dict(node)
    return d.pop("name"), d


def compose_config(overrides: list[str]):
    """The training config ``facesynth train OVERRIDES`` runs with, composed by Hydra from
    the package's ``conf/`` (without the ``hydra`` node). Bad overrides raise
    FacesynthError naming them."""
    if not (CONF_DIR / "config.yaml").is_file():
        raise FacesynthError(f"{CONF_DIR}: Hydra configs not found (a broken installation: reinstall facesynth)")
    register_configs()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name="config", overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as exc:
        msg = " ".join(str(exc).split())
        raise FacesynthError(f"training config overrides {list(overrides)}: {msg}") from None


def train_defaults(regressor: str) -> tuple[str, dict, SADMConfig]:
    """What ``python train.py regressor=NAME`` trains with: the regressor's name and
    hyper-parameters and the SADM settings (a regressor's config may set some, e.g. krr's
    augmentation), composed by Hydra from the package's ``conf/`` (for benchmarks and
    scripts that call :func:`facesynth.sadm.fit.fit_sadm` directly)."""
    cfg = compose_config([f"regressor={regressor}"])
    name, params = regressor_params(cfg.regressor)
    return name, params, resolve_sadm_config(name, SADMConfig(**OmegaConf.to_container(cfg.sadm, resolve=True)))
