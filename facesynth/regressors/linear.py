"""The linear SADM (Eq. 5 of the paper): A = G S^T (S S^T)^-1 with a bias, optional ridge."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from facesynth.regressors._common import LOG_RIDGE, as_config
from facesynth.regressors.base import Regressor, register

RCOND = 1e-10  # singular values of the Gram matrix below RCOND * largest are treated as 0


@dataclass
class LinearConfig:
    """ridge: lambda of ||A||^2 (the bias is not penalised); 10 regularises the nearly
    collinear aligned-landmark inputs (0 is the paper's plain least squares)."""

    ridge: float = 10.0


@register("linear")
class LinearRegressor(Regressor):
    """y = x W^T + b. Forward: (B, D_in) -> (B, D_out)."""

    config_class = LinearConfig
    search_grid = {"ridge_rel": list(LOG_RIDGE)}

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, ridge: float = 0.0):
        super().__init__()
        self.register_buffer("weight", weight.float())
        self.register_buffer("bias", bias.float())
        self.ridge = float(ridge)

    @classmethod
    def fit(cls, x, y, config=None, x_val=None, y_val=None, seed=0):
        cfg = as_config(LinearConfig, config, "regressor linear")  # also mappings / DictConfig
        ridge = float(cfg.ridge)
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        mx, my = x.mean(0), y.mean(0)
        xc, yc = x - mx, y - my
        # Closed form on centred data: the bias absorbs the means (unpenalised).
        gram = xc.T @ xc + ridge * np.eye(x.shape[1])
        # Minimum-norm solution: directions the inputs never vary in (aligned landmarks have
        # exact similarity constraints: eigenvalues ~1e-13 of the largest) get zero weight,
        # instead of weights ~1e4 that turn float32 rounding of the inputs into texture error.
        w = np.linalg.lstsq(gram, xc.T @ yc, rcond=RCOND)[0].T  # (D_out, D_in)
        b = my - w @ mx
        return cls(torch.from_numpy(w), torch.from_numpy(b), ridge)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.matmul(x, self.weight.t()) + self.bias

    def config_dict(self) -> dict:
        return {"ridge": self.ridge}

    @classmethod
    def from_state(cls, config, tensors):
        return cls(tensors["weight"], tensors["bias"], config.get("ridge", 0.0))
