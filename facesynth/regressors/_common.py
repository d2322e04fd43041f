"""Helpers shared by the regressors: config coercion, input checks, standardisation."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from facesynth.errors import FacesynthError

LOG_RIDGE = [1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3]  # the relative-ridge search grid (key ridge_rel) of linear and poly2


def as_config(cls: type, config: Any, where: str):
    """Coerce ``config`` (None, a ``cls`` instance, a mapping or an OmegaConf node) to ``cls``.

    Unknown keys raise :class:`FacesynthError` naming the regressor and the key, so that
    a typo in a config file fails early instead of silently using a default.
    """
    if config is None:
        return cls()
    if isinstance(config, cls):
        return config
    if dataclasses.is_dataclass(config):
        config = dataclasses.asdict(config)
    elif not isinstance(config, Mapping):
        try:  # OmegaConf DictConfig
            from omegaconf import OmegaConf

            config = OmegaConf.to_container(config, resolve=True)
        except Exception as exc:  # pragma: no cover - defensive
            raise FacesynthError(f"{where}: config must be a {cls.__name__} or a mapping, got {type(config).__name__}") from exc
    names = {f.name for f in dataclasses.fields(cls)}
    extra = sorted(set(config) - names)
    if extra:
        raise FacesynthError(f"{where}: unknown config key(s) {extra}; expected some of {sorted(names)}")
    return cls(**dict(config))


def check_xy(x, y, where: str, min_rows: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Validate (N, D_in) inputs and (N, D_out) targets; return float64 copies."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.ndim != 2:
        raise FacesynthError(f"{where}: inputs must be a 2-D (N, D_in) array, got shape {x.shape}")
    if y.ndim != 2:
        raise FacesynthError(f"{where}: targets must be a 2-D (N, D_out) array, got shape {y.shape}")
    if len(x) != len(y):
        raise FacesynthError(f"{where}: inputs have {len(x)} rows but targets have {len(y)}")
    if len(x) < min_rows:
        raise FacesynthError(f"{where}: need at least {min_rows} training rows, got {len(x)}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise FacesynthError(f"{where}: inputs/targets contain NaN or inf")
    return x, y


def standardiser(a: np.ndarray, eps: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Column mean and standard deviation of (N, D) ``a``; constant columns get scale 1
    (as scikit-learn's ``StandardScaler``)."""
    mean = a.mean(0)
    std = a.std(0)
    std = np.where(std < eps * np.maximum(1.0, np.abs(mean)), 1.0, std)
    return mean, std


def tail_holdout(n: int, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Split ``n`` temporally ordered rows into (leading train, trailing validation) indices.

    The validation slice is the LAST ``fraction`` of the rows (never a random subset:
    neighbouring video frames are near copies, so a random split would leak).
    """
    n_val = max(1, int(round(n * fraction)))
    if n - n_val < 2:
        raise FacesynthError(f"too few rows ({n}) to hold out a validation slice of {fraction:.0%}")
    return np.arange(n - n_val), np.arange(n - n_val, n)
