"""The driving model: FAP vector -> eigenERI coefficients, one support vector regressor per
coefficient (epsilon-SVR or nu-SVR, linear or RBF kernel; scikit-learn's libsvm fits them).

V. Vapnik, "The Nature of Statistical Learning Theory", 1995 (epsilon-SVR);
B. Schoelkopf et al., "New support vector algorithms", Neural Computation 12, 2000 (nu-SVR).

Inputs are standardised (training mean and standard deviation); each target coefficient
is standardised too, so ``epsilon`` is in units of that coefficient's standard deviation.
The fitted machines are kept as plain tensors (support vectors, dual coefficients,
intercepts) and evaluated as one batched kernel product, so prediction needs no
scikit-learn and saving needs no pickle:

    y_k(x) = s_k (sum_{j in SV_k} alpha_j K(z_j, z) + b_k) + m_k,   z = (x - mu) / sigma
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from facesynth.errors import FacesynthError
from facesynth.metrics import ncc
from facesynth.progress import bar as progress_bar
from facesynth.regressors.base import Regressor

VARIANTS = {"eps_linear": ("eps", "linear"), "eps_rbf": ("eps", "rbf"), "nu_linear": ("nu", "linear"), "nu_rbf": ("nu", "rbf")}


class SVRBank(Regressor):
    """K independent SVRs evaluated together. Forward: (B, D) FAPs -> (B, K) coefficients."""

    name = "svr_bank"

    def __init__(self, sv, dual, owner, intercept, x_mean, x_std, y_mean, y_scale, kernel: str, gamma: float, params: dict | None = None):
        super().__init__()
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt)  # noqa: E731
        k = len(intercept)
        w = torch.zeros(len(dual), k)
        w[torch.arange(len(dual)), t(owner, torch.int64)] = t(dual)
        for name, val in (("sv", t(sv)), ("weights", w), ("intercept", t(intercept)), ("x_mean", t(x_mean)),
                          ("x_std", t(x_std)), ("y_mean", t(y_mean)), ("y_scale", t(y_scale)),
                          ("owner", t(owner, torch.int64)), ("dual", t(dual))):
            self.register_buffer(name, val)
        self.kernel, self.gamma, self.params = kernel, float(gamma), dict(params or {})

    @classmethod
    def fit(cls, x, y, config=None, x_val=None, y_val=None, seed=0):
        """Fit one SVR per column of y (N, K) on x (N, D).

        ``config``: dict with ``variant`` (a key of ``VARIANTS``), ``C``, ``epsilon``, ``nu``,
        ``gamma`` ("scale" = 1 / D on standardised inputs, or a float multiplier of it).
        """
        from sklearn.svm import SVR, NuSVR

        cfg = dict(config or {})
        if cfg.get("variant") not in VARIANTS:
            raise FacesynthError(f"SVR variant must be one of {list(VARIANTS)}, got {cfg.get('variant')!r}")
        kind, kernel = VARIANTS[cfg["variant"]]
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        x_mean, x_std = x.mean(0), x.std(0)
        x_std = np.where(x_std > 1e-8, x_std, 1.0)
        y_mean, y_scale = y.mean(0), y.std(0)
        y_scale = np.where(y_scale > 1e-12, y_scale, 1.0)
        z, t = (x - x_mean) / x_std, (y - y_mean) / y_scale
        g = cfg.get("gamma", "scale")
        gamma = (1.0 if g == "scale" else float(g)) / x.shape[1]
        common = dict(kernel=kernel, C=float(cfg.get("C", 1.0)), gamma=gamma, cache_size=200)
        svs, duals, owners, b = [], [], [], []
        for k in progress_bar(range(y.shape[1]), desc=f"SVR {cfg['variant']}", unit="fit"):
            if kind == "eps":
                m = SVR(epsilon=float(cfg.get("epsilon", 0.1)), **common)
            else:
                m = NuSVR(nu=float(cfg.get("nu", 0.5)), **common)
            m.fit(z, t[:, k])
            svs.append(m.support_vectors_)
            duals.append(m.dual_coef_[0])
            owners.append(np.full(len(m.support_), k))
            b.append(float(m.intercept_[0]))
        params = {k: cfg[k] for k in ("variant", "C", "epsilon", "nu", "gamma") if k in cfg}
        return cls(np.concatenate(svs), np.concatenate(duals), np.concatenate(owners), b,
                   x_mean, x_std, y_mean, y_scale, kernel, gamma, params)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = (x - self.x_mean) / self.x_std
        if self.kernel == "linear":
            out = z @ (self.sv.t() @ self.weights)
        else:
            d2 = (z * z).sum(1, keepdim=True) - 2 * z @ self.sv.t() + (self.sv * self.sv).sum(1)
            out = torch.exp(-self.gamma * d2.clamp_min(0)) @ self.weights
        return (out + self.intercept) * self.y_scale + self.y_mean

    def config_dict(self) -> dict:
        return {"kernel": self.kernel, "gamma": self.gamma, "params": self.params}

    @classmethod
    def from_state(cls, config, tensors):
        t = {k: v.numpy() for k, v in tensors.items()}
        return cls(t["sv"], t["dual"], t["owner"], t["intercept"], t["x_mean"], t["x_std"], t["y_mean"],
                   t["y_scale"], config["kernel"], config["gamma"], config.get("params"))

    def summary(self) -> dict:
        return {"support_vectors": int(len(self.sv)), **self.params}


def fit_variant(variant: str, x, y, cfg, x_val=None, y_val=None) -> tuple[SVRBank, dict]:
    """Fit ``variant`` with the config's hyper-parameters, or, when ``cfg.grid_search`` and a
    validation slice are given, pick C (and gamma for RBF) from ``cfg.C_grid`` x
    ``cfg.gamma_grid`` by validation MSE (standardised coefficients), then refit on
    ``x`` + validation. Returns the bank and {"params", "val_mse"}."""
    base = {"variant": variant, "C": cfg.C, "epsilon": cfg.epsilon, "nu": cfg.nu, "gamma": cfg.gamma}
    if not (cfg.grid_search and x_val is not None and len(x_val)):
        return SVRBank.fit(x, y, base), {"params": base, "val_mse": None}
    scale = np.asarray(y, np.float64).std(0) + 1e-12
    gammas = cfg.gamma_grid if VARIANTS[variant][1] == "rbf" else [cfg.gamma]
    results = []
    for c, g in itertools.product(cfg.C_grid, gammas):
        p = {**base, "C": float(c), "gamma": g}
        pred = SVRBank.fit(x, y, p).predict(x_val)
        results.append((float((((pred - y_val) / scale) ** 2).mean()), p))
    best_mse, best = min(results, key=lambda r: r[0])
    xa, ya = np.concatenate([x, x_val]), np.concatenate([y, y_val])
    return SVRBank.fit(xa, ya, best), {"params": best, "val_mse": best_mse,
                                       "grid": [{"C": p["C"], "gamma": p["gamma"], "val_mse": m} for m, p in results]}


def choose_driver(report: dict) -> tuple[str, str]:
    """The synthesis driver from the variants' validation MSE (``report[v]["val_mse"]``,
    standardised coefficients): the best linear variant, replaced by an RBF variant only
    when that one is strictly better on validation. Returns (variant, rule)."""
    linear = [v for v in report if VARIANTS[v][1] == "linear"]
    best = min(report, key=lambda v: report[v]["val_mse"])
    if not linear:
        return best, "lowest validation MSE"
    base = min(linear, key=lambda v: report[v]["val_mse"])
    if best != base and report[best]["val_mse"] < report[base]["val_mse"]:
        return best, f"lowest validation MSE ({report[best]['val_mse']:.3f} < best linear {base} {report[base]['val_mse']:.3f})"
    return base, f"best linear variant on validation (MSE {report[base]['val_mse']:.3f})"


def coefficient_scores(pred: np.ndarray, true: np.ndarray) -> dict:
    """The paper's Fig. 5 figures for (N, K) predicted vs true coefficients: mean squared
    error (raw units, and normalised by each coefficient's test variance) and the squared
    correlation coefficient r^2, averaged over the K coefficients (and per coefficient)."""
    p, t = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    mse_k = ((p - t) ** 2).mean(0)
    var_k = t.var(0)
    r2_k = ncc(p, t) ** 2
    return {
        "mse": float(mse_k.mean()),
        "nmse": float((mse_k / np.where(var_k > 0, var_k, 1)).mean()),
        "r2": float(r2_k.mean()),
        "r2_first5": float(r2_k[:5].mean()),
        "explained_variance": float(1.0 - mse_k.sum() / max(var_k.sum(), 1e-30)),
        "mse_per_coefficient": mse_k.tolist(),
        "r2_per_coefficient": r2_k.tolist(),
    }
