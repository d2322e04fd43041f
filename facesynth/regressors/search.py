"""Grid search of regressor hyper-parameters on a validation slice.

The validation slice must be the later part of the TRAINING segment (never the test
frames). Score: mean squared error of the predicted outputs, optionally weighted per
output, ``mean_n mean_j w_j (y_hat_nj - y_nj)^2``; lower is better, ties keep the first.

The grid key ``ridge_rel`` (linear, poly2) is relative and resolved on the training
inputs before fitting: ``ridge = ridge_rel * trace(Phi_c^T Phi_c) / N`` where
  Phi_c are the centred regression features (raw inputs for linear, the standardised
  quadratic features for poly2), so one grid fits any input scale and dimension
  (poly2 with ``relative_ridge=True``, its default, applies that scaling itself).
For the SVR, ``gamma_mult`` is a config field: gamma = gamma_mult * 'scale' (1 / (D var(z))).
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from typing import Any

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.regressors._common import as_config, check_xy
from facesynth.regressors.base import REGISTRY
from facesynth.regressors.poly2 import design as poly2_design


def config_class(name: str) -> type:
    """The config dataclass of regressor ``name``."""
    if name not in REGISTRY:
        raise FacesynthError(f"unknown regressor {name!r}; expected one of {sorted(REGISTRY)}")
    return REGISTRY[name].config_class


def _ridge_unit(name: str, x: np.ndarray, cfg) -> float:
    """trace(Phi_c^T Phi_c) / N = sum of the feature variances."""
    phi = poly2_design(x, cfg)[3] if name == "poly2" else x  # the features poly2.fit regresses on
    return float(phi.var(0).sum())


def resolve(name: str, params: dict[str, Any], x: np.ndarray, base) -> Any:
    """A config of regressor ``name`` from ``base`` with ``params`` applied (the relative
    key ``ridge_rel`` turned into ``ridge`` on ``x``)."""
    params = dict(params)
    fields = {f.name for f in dataclasses.fields(base)} | {"ridge_rel"}
    unknown = sorted(set(params) - fields)
    if unknown:
        raise FacesynthError(f"search {name}: unknown grid key(s) {unknown}; expected some of {sorted(fields)}")
    cfg = dataclasses.replace(base, **{k: v for k, v in params.items() if k != "ridge_rel"})
    if "ridge_rel" in params:
        if name not in ("linear", "poly2"):
            raise FacesynthError(f"grid key 'ridge_rel' applies to linear/poly2, not {name!r}")
        rel = float(params["ridge_rel"])
        if getattr(cfg, "relative_ridge", False):  # poly2 already scales its ridge
            cfg = dataclasses.replace(cfg, ridge=rel)
        else:
            cfg = dataclasses.replace(cfg, ridge=rel * _ridge_unit(name, x, cfg))
    return cfg


def weighted_mse(pred: np.ndarray, true: np.ndarray, weights: np.ndarray | None = None) -> float:
    """mean over rows and outputs of w_j (pred - true)^2 (w = 1 by default)."""
    err = (np.asarray(pred, np.float64) - np.asarray(true, np.float64)) ** 2
    if weights is not None:
        err = err * np.asarray(weights, np.float64)[None, :]
    return float(err.mean())


def search(
    name: str,
    x_tr: np.ndarray,
    y_tr: np.ndarray,
    x_val: np.ndarray,
    y_val: np.ndarray,
    grid: dict[str, list] | None = None,
    base_config: Any = None,
    seed: int = 0,
    weights: np.ndarray | None = None,
) -> tuple[Any, list[dict]]:
    """Try every combination of ``grid`` (default the regressor's ``search_grid``); fit on
    (x_tr, y_tr), score on (x_val, y_val).

    Parameters
    ----------
    x_tr, y_tr : (N, D_in), (N, D_out) training rows.
    x_val, y_val : (M, D_in), (M, D_out) validation rows (later in time than x_tr).
    grid : mapping key -> list of values (config fields, or ``ridge_rel``).
    base_config : config of the other fields (dataclass or mapping; default: defaults).
    weights : optional (D_out,) per-output weights of the score.

    Returns
    -------
    best_config : the config dataclass (absolute values) with the lowest validation score.
    table : one dict per setting, in grid order: the grid values, ``config`` (the absolute
      config as a dict), ``val_mse``, ``fit_seconds``, ``best`` (bool).
    """
    cls = config_class(name)
    base = as_config(cls, base_config, f"regressor {name}")
    x_tr, y_tr = check_xy(x_tr, y_tr, f"search {name} (training rows)")
    x_val, y_val = check_xy(x_val, y_val, f"search {name} (validation rows)", min_rows=1)
    if x_val.shape[1] != x_tr.shape[1] or y_val.shape[1] != y_tr.shape[1]:
        raise FacesynthError(f"search {name}: validation columns {x_val.shape[1:]}/{y_val.shape[1:]} differ from training")
    if weights is not None and np.shape(weights) != (y_tr.shape[1],):
        raise FacesynthError(f"search {name}: weights must have shape ({y_tr.shape[1]},), got {np.shape(weights)}")
    grid = REGISTRY[name].search_grid if grid is None else grid
    if not grid or any(len(v) == 0 for v in grid.values()):
        raise FacesynthError(f"search {name}: grid must give at least one value per key, got {grid}")
    keys = list(grid)
    table: list[dict] = []
    best_cfg, best_score = None, np.inf
    for values in itertools.product(*(grid[k] for k in keys)):
        params = dict(zip(keys, values, strict=True))
        cfg = resolve(name, params, x_tr, base)
        t0 = time.perf_counter()
        reg = REGISTRY[name].fit(x_tr, y_tr, cfg, seed=seed)
        fit_s = time.perf_counter() - t0
        score = weighted_mse(reg.predict(x_val), y_val, weights)
        table.append({**params, "config": dataclasses.asdict(cfg), "val_mse": score, "fit_seconds": fit_s, "best": False})
        if score < best_score:
            best_cfg, best_score = cfg, score
    for row in table:
        row["best"] = row["val_mse"] == best_score
        if row["best"]:
            break
    return best_cfg, table
