"""Second-order polynomial regressor: quadratic features of standardised inputs + ridge.

Features of z = (x - mu) / sigma (D_in = D): the D linear terms (optional) and the
D (D + 1) / 2 products z_i z_j, i <= j (squares included); a bias absorbs the means and
is not penalised. The ridge solution is the closed form on centred features, solved in
the primal (F x F) or the dual (N x N, kernel ridge with the explicit quadratic kernel)
whichever is smaller -- both give the same weights. This is the same model as
scikit-learn's ``StandardScaler -> PolynomialFeatures(2, include_bias=False) -> Ridge``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.linalg
import torch

from facesynth.regressors._common import LOG_RIDGE, as_config, check_xy, standardiser
from facesynth.regressors.base import Regressor, register


@dataclass
class Poly2Config:
    ridge: float = 100.0  # lambda of ||W||^2 on the polynomial features (bias not penalised)
    relative_ridge: bool = True  # lambda = ridge * trace(Phi_c^T Phi_c) / N (scale-free); else absolute
    include_linear: bool = True  # keep the D linear terms next to the D(D+1)/2 products
    standardise: bool = True  # z-score the inputs before forming products
    # project (standardised) inputs on their leading K whitened PCs first (None: all inputs);
    # quadratic terms of all 136 landmark coordinates extrapolate below the mean texture on
    # clips whose test segment holds unseen expressions (docs/regressors.md)
    input_components: Optional[int] = 16


def triu_flat_index(d: int) -> np.ndarray:
    """Flat indices i * d + j of the upper triangle (i <= j) of a (d, d) matrix, row-major
    (the order of scikit-learn's ``PolynomialFeatures`` degree-2 block)."""
    i, j = np.triu_indices(d)
    return (i * d + j).astype(np.int64)


def poly2_features(z: np.ndarray, include_linear: bool = True) -> np.ndarray:
    """(N, D) -> (N, F) float64 features [z, z_i z_j (i <= j)]."""
    z = np.asarray(z, np.float64)
    quad = (z[:, :, None] * z[:, None, :]).reshape(len(z), -1)[:, triu_flat_index(z.shape[1])]
    return np.concatenate([z, quad], 1) if include_linear else quad


def ridge_closed_form(phi: np.ndarray, y: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge with an unpenalised bias: returns W (D_out, F), b (D_out,).

    Primal  W^T = (Phi_c^T Phi_c + lambda I)^-1 Phi_c^T Y_c   when F <= N,
    dual    W^T = Phi_c^T (Phi_c Phi_c^T + lambda I)^-1 Y_c   otherwise (same solution).
    """
    mphi, my = phi.mean(0), y.mean(0)
    pc, yc = phi - mphi, y - my
    n, f = pc.shape
    if f <= n:
        gram = pc.T @ pc
        rhs = pc.T @ yc
        if ridge > 0:
            gram[np.diag_indices(f)] += ridge
            wt = scipy.linalg.solve(gram, rhs, assume_a="pos")
        else:
            wt = np.linalg.lstsq(gram, rhs, rcond=None)[0]
    else:
        k = pc @ pc.T
        if ridge > 0:
            k[np.diag_indices(n)] += ridge
            alpha = scipy.linalg.solve(k, yc, assume_a="pos")
        else:
            alpha = np.linalg.lstsq(k, yc, rcond=None)[0]
        wt = pc.T @ alpha
    w = wt.T
    return w, my - w @ mphi


def design(x: np.ndarray, cfg: Poly2Config) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The regression design of (N, D) inputs: standardiser mean and scale (D,), projection
    (D, d) (identity, or the leading whitened principal components) and the (N, F)
    polynomial features."""
    if cfg.standardise:
        mu, sd = standardiser(x)
    else:
        mu, sd = np.zeros(x.shape[1]), np.ones(x.shape[1])
    z = (x - mu) / sd
    proj = np.eye(x.shape[1])
    if cfg.input_components:
        # Quadratic features of many correlated inputs (e.g. 136 landmark coordinates)
        # extrapolate wildly; a few whitened principal components keep them in check.
        zc = z - z.mean(0)
        _, sv, vt = np.linalg.svd(zc, full_matrices=False)
        k = min(int(cfg.input_components), len(sv))
        proj = vt[:k].T / np.maximum(sv[:k] / np.sqrt(max(len(z) - 1, 1)), 1e-12)
        z = (x - mu) / sd @ proj
    return mu, sd, proj, poly2_features(z, cfg.include_linear)


@register("poly2")
class Poly2Regressor(Regressor):
    """y = W [z, z_i z_j] + b with z = (x - mu) / sigma. Forward: (B, D_in) -> (B, D_out).

    The quadratic block is an outer product flattened and gathered with a fixed index
    buffer (``triu``), so the graph is plain tensor ops (exports to ONNX).
    """

    config_class = Poly2Config
    search_grid = {"ridge_rel": list(LOG_RIDGE)}

    def __init__(self, x_mean, x_scale, weight, bias, config: Poly2Config, proj=None):
        super().__init__()
        self.config = config
        proj = torch.eye(int(x_mean.shape[0])) if proj is None else torch.as_tensor(proj)
        self.register_buffer("x_mean", torch.as_tensor(x_mean).float())
        self.register_buffer("x_scale", torch.as_tensor(x_scale).float())
        self.register_buffer("proj", proj.float())  # (D, d): identity, or whitened leading PCs
        self.register_buffer("triu", torch.from_numpy(triu_flat_index(int(proj.shape[1]))))
        self.register_buffer("weight", torch.as_tensor(weight).float())
        self.register_buffer("bias", torch.as_tensor(bias).float())
        self.lam = float("nan")  # the absolute lambda used by fit

    @classmethod
    def fit(cls, x, y, config=None, x_val=None, y_val=None, seed=0):
        cfg = as_config(Poly2Config, config, "regressor poly2")
        x, y = check_xy(x, y, "regressor poly2")
        mu, sd, proj, phi = design(x, cfg)
        lam = float(cfg.ridge) * (float(phi.var(0).sum()) if cfg.relative_ridge else 1.0)
        w, b = ridge_closed_form(phi, y, lam)
        reg = cls(torch.from_numpy(mu), torch.from_numpy(sd), torch.from_numpy(w), torch.from_numpy(b), cfg,
                  torch.from_numpy(proj))
        reg.lam = lam
        return reg

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B, F) polynomial features (torch)."""
        z = torch.matmul((x - self.x_mean) / self.x_scale, self.proj)
        outer = (z.unsqueeze(2) * z.unsqueeze(1)).reshape(z.shape[0], -1)
        quad = torch.index_select(outer, 1, self.triu)
        return torch.cat([z, quad], 1) if self.config.include_linear else quad

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.matmul(self.features(x), self.weight.t()) + self.bias

    def config_dict(self) -> dict:
        return {
            "ridge": float(self.config.ridge),
            "relative_ridge": bool(self.config.relative_ridge),
            "lambda": self.lam,
            "include_linear": bool(self.config.include_linear),
            "standardise": bool(self.config.standardise),
            "input_components": self.config.input_components,
        }

    @classmethod
    def from_state(cls, config, tensors):
        config = dict(config)
        lam = config.pop("lambda", float("nan"))
        reg = cls(tensors["x_mean"], tensors["x_scale"], tensors["weight"], tensors["bias"],
                  as_config(Poly2Config, config, "regressor poly2"), tensors.get("proj"))
        reg.lam = float(lam)
        return reg

    def summary(self) -> dict:
        return {"n_features": int(self.weight.shape[1]), "ridge": float(self.config.ridge), "lambda": self.lam}
