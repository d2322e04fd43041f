"""Support vector regression per output (scikit-learn / libsvm), exact kernel expansion in torch.

Training: one ``sklearn.svm.SVR`` (epsilon-SVR, Vapnik 1995) or ``NuSVR`` (nu-SVR,
Schoelkopf et al. 2000) per output dimension on standardised inputs and targets.

Inference is the SVM decision function written as tensor ops (no scikit-learn at run
time, exports to ONNX). With the UNION of the support vectors of all outputs
SV (S, D) and a dense dual-coefficient matrix alpha (D_out, S) (zero where an SV is not
used by that output)::

    RBF:     y_j = sum_i alpha_ji exp(-gamma ||z - sv_i||^2) + b_j      one (B, S) kernel, one matmul
    linear:  y_j = sum_i alpha_ji <z, sv_i> + b_j = (alpha SV) z + b    folded to a weight matrix

with ||z - sv||^2 = ||z||^2 + ||sv||^2 - 2 z sv^T (clamped >= 0). The input
standardisation and sqrt(gamma) are folded into a per-feature shift/scale and the stored SVs,
the target standardisation into alpha and b, so ``forward`` maps raw x to raw y.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from joblib import Parallel, delayed

from facesynth.errors import FacesynthError
from facesynth.progress import bar as progress_bar
from facesynth.regressors._common import as_config, check_xy, standardiser
from facesynth.regressors.base import Regressor, register


@dataclass
class SVRConfig:
    kind: str = "epsilon"  # "epsilon" (sklearn SVR) | "nu" (sklearn NuSVR)
    kernel: str = "rbf"  # "rbf" | "linear"
    C: float = 1.0
    epsilon: float = 0.1  # epsilon-SVR tube width (standardised target units)
    nu: float = 0.5  # nu-SVR
    gamma: Any = "scale"  # "scale" (1 / (D var(z))), "auto" (1 / D) or a float
    gamma_mult: float = 0.25  # multiplies gamma (0.25: best on a validation slice, docs/regressors.md)
    standardise: bool = True  # z-score inputs and targets (per output)
    tol: float = 1e-3
    cache_size: float = 200.0
    n_jobs: int = 1  # joblib workers over outputs


def resolve_gamma(gamma: Any, z: np.ndarray) -> float:
    """scikit-learn's gamma rule on the (standardised) training inputs z (N, D)."""
    if isinstance(gamma, str):
        if gamma == "scale":
            var = float(z.var())
            return 1.0 / (z.shape[1] * var) if var > 0 else 1.0
        if gamma == "auto":
            return 1.0 / z.shape[1]
        raise FacesynthError(f"regressor svr: gamma must be 'scale', 'auto' or a float, got {gamma!r}")
    g = float(gamma)
    if not g > 0:
        raise FacesynthError(f"regressor svr: gamma must be > 0, got {g}")
    return g


def _fit_one(kind, params, z, t):
    from sklearn.svm import SVR, NuSVR

    est = SVR(**params) if kind == "epsilon" else NuSVR(**params)
    est.fit(z, np.ascontiguousarray(t))
    return est.support_.astype(np.int64), est.dual_coef_.ravel().astype(np.float64), float(est.intercept_[0]), est


@register("svr")
class SVRRegressor(Regressor):
    """Forward: (B, D_in) raw inputs -> (B, D_out) raw outputs (exact SVM decision function)."""

    config_class = SVRConfig
    # gamma_mult reaches below 0.25, the best value of an earlier grid's low edge (docs/regressors.md)
    search_grid = {"C": [0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0], "gamma_mult": [0.0625, 0.125, 0.25, 0.5, 1.0, 2.0]}

    def __init__(self, config: SVRConfig, tensors: dict[str, torch.Tensor], info: dict):
        super().__init__()
        self.config = config
        self.info = dict(info)
        for k, v in tensors.items():
            self.register_buffer(k, torch.as_tensor(v).float())

    @staticmethod
    def check_config(cfg: SVRConfig) -> None:
        if cfg.kind not in ("epsilon", "nu"):
            raise FacesynthError(f"regressor svr: kind must be 'epsilon' or 'nu', got {cfg.kind!r}")
        if cfg.kernel not in ("rbf", "linear"):
            raise FacesynthError(f"regressor svr: kernel must be 'rbf' or 'linear', got {cfg.kernel!r}")

    @classmethod
    def standardise(cls, x: np.ndarray, cfg: SVRConfig) -> tuple[np.ndarray, np.ndarray]:
        """Input mean and scale used for training (identity when ``standardise`` is off)."""
        if cfg.standardise:
            return standardiser(x)
        return np.zeros(x.shape[1]), np.ones(x.shape[1])

    @classmethod
    def fit(cls, x, y, config=None, x_val=None, y_val=None, seed=0):
        cfg = as_config(SVRConfig, config, "regressor svr")
        cls.check_config(cfg)
        x, y = check_xy(x, y, "regressor svr")
        mx, sx = cls.standardise(x, cfg)
        if cfg.standardise:
            my, sy = standardiser(y)
        else:
            my, sy = np.zeros(y.shape[1]), np.ones(y.shape[1])
        z, t = (x - mx) / sx, (y - my) / sy
        gamma = resolve_gamma(cfg.gamma, z) * float(cfg.gamma_mult)
        if not gamma > 0:
            raise FacesynthError(f"regressor svr: gamma_mult must be > 0, got {cfg.gamma_mult}")
        params = {"kernel": cfg.kernel, "C": float(cfg.C), "tol": float(cfg.tol), "cache_size": float(cfg.cache_size)}
        if cfg.kernel == "rbf":
            params["gamma"] = gamma
        if cfg.kind == "epsilon":
            params["epsilon"] = float(cfg.epsilon)
        else:
            params["nu"] = float(cfg.nu)
        outputs = progress_bar(range(y.shape[1]), desc=f"SVR {cfg.kind}", unit="fit")
        fits = Parallel(n_jobs=int(cfg.n_jobs))(delayed(_fit_one)(cfg.kind, params, z, t[:, j]) for j in outputs)

        union = np.unique(np.concatenate([s for s, *_ in fits])) if fits else np.zeros(0, np.int64)
        pos = np.searchsorted(union, np.arange(len(x)))  # row -> column in the union (valid where member)
        coef = np.zeros((y.shape[1], len(union)))
        for j, (sup, dual, *_) in enumerate(fits):
            coef[j, pos[sup]] = dual
        b = np.array([f[2] for f in fits])
        sv = z[union]  # (S, D) standardised
        # fold the target standardisation: y = (coef K + b) * sy + my
        coef_y = coef * sy[:, None]
        b_y = b * sy + my
        info = {
            "gamma": gamma if cfg.kernel == "rbf" else None,
            "n_support_union": int(len(union)),
            "n_support_per_output": [int(len(s)) for s, *_ in fits],
        }
        if cfg.kernel == "rbf":
            # sqrt(gamma) z = (x - shift) * scale; the shift is subtracted BEFORE the
            # expansion so that ||.||^2 stays O(gamma D) and float32 cancellation is small.
            g = np.sqrt(gamma)
            sv_g = g * sv
            tensors = {"shift": mx, "scale": g / sx, "sv": sv_g, "sv_sq": (sv_g**2).sum(1), "coef": coef_y, "bias": b_y}
        else:
            w_std = coef_y @ sv  # (D_out, D) on z
            w = w_std / sx[None, :]
            tensors = {"weight": w, "bias": b_y - w @ mx}
        model = cls(cfg, {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in tensors.items()}, info)
        # the fitted scikit-learn models on standardised data (not saved; for checks/debugging)
        model.estimators_ = [f[3] for f in fits]
        model.standardisation_ = {"x_mean": mx, "x_scale": sx, "y_mean": my, "y_scale": sy}
        return model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.config.kernel == "linear":
            return torch.matmul(x, self.weight.t()) + self.bias
        xs = (x - self.shift) * self.scale
        d2 = (xs * xs).sum(1, keepdim=True) + self.sv_sq - 2.0 * torch.matmul(xs, self.sv.t())
        k = torch.exp(-torch.clamp(d2, min=0.0))
        return torch.matmul(k, self.coef.t()) + self.bias

    def config_dict(self) -> dict:
        c = self.config
        gamma = c.gamma if isinstance(c.gamma, str) else float(c.gamma)
        return {
            "kind": c.kind, "kernel": c.kernel, "C": float(c.C), "epsilon": float(c.epsilon), "nu": float(c.nu),
            "gamma": gamma, "gamma_mult": float(c.gamma_mult), "standardise": bool(c.standardise), "tol": float(c.tol),
            "cache_size": float(c.cache_size), "n_jobs": int(c.n_jobs), "info": self.info,
        }

    @classmethod
    def from_state(cls, config, tensors):
        config = dict(config)
        info = config.pop("info", {})
        cfg = as_config(SVRConfig, config, "regressor svr")
        cls.check_config(cfg)
        return cls(cfg, dict(tensors), info)

    def summary(self) -> dict:
        per = self.info.get("n_support_per_output", [])
        return {
            "n_support_union": self.info.get("n_support_union"),
            "n_support_mean_per_output": float(np.mean(per)) if per else 0.0,
            "gamma": self.info.get("gamma"),
        }
