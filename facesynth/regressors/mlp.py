"""Multi-layer perceptron regressor (torch), AdamW with early stopping on a validation slice.

Inputs and targets are standardised for training (targets by their mean and either one
global scale -- so that the loss is proportional to the mean squared error in b_g space,
the quantity that texture PSNR measures, since the appearance basis is orthonormal -- or
one scale per output). After training the standardisation is folded into the first and
last ``Linear`` layers, so ``forward`` takes raw inputs and returns raw outputs.

Early stopping (Prechelt, "Early stopping -- but when?", 1998): the weights of the epoch
with the lowest validation loss are kept; training stops after ``patience`` epochs
without improvement or at ``max_epochs``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from facesynth.errors import FacesynthError
from facesynth.progress import bar as progress_bar
from facesynth.regressors._common import as_config, check_xy, standardiser, tail_holdout
from facesynth.regressors.base import Regressor, register

ACTIVATIONS = {"relu": nn.ReLU, "gelu": nn.GELU, "tanh": nn.Tanh, "silu": nn.SiLU, "elu": nn.ELU}


@dataclass
class MLPConfig:
    hidden: list[int] = field(default_factory=lambda: [128, 128])  # hidden layer widths
    activation: str = "gelu"  # one of ACTIVATIONS
    weight_decay: float = 1.0  # AdamW decoupled weight decay (1 and dropout 0.2: best on a validation slice)
    lr: float = 1e-3
    max_epochs: int = 300  # caps the training time
    patience: int = 30  # epochs without validation improvement before stopping
    batch_size: int = 64
    dropout: float = 0.2
    val_fraction: float = 0.15  # trailing share held out when no x_val is given
    target_scaling: str = "global"  # "global" (one scale, MSE in b_g space) | "per_output"


def build_net(d_in: int, d_out: int, cfg: MLPConfig) -> nn.Sequential:
    """Linear -> act (-> dropout) ... -> Linear."""
    if cfg.activation not in ACTIVATIONS:
        raise FacesynthError(f"regressor mlp: activation must be one of {sorted(ACTIVATIONS)}, got {cfg.activation!r}")
    layers: list[nn.Module] = []
    prev = d_in
    for h in cfg.hidden:
        layers += [nn.Linear(prev, int(h)), ACTIVATIONS[cfg.activation]()]
        if cfg.dropout > 0:
            layers.append(nn.Dropout(cfg.dropout))
        prev = int(h)
    layers.append(nn.Linear(prev, d_out))
    return nn.Sequential(*layers)


def _fold(net: nn.Sequential, mx, sx, my, sy) -> None:
    """Fold z = (x - mx) / sx into the first layer and y = out * sy + my into the last."""
    first, last = net[0], net[-1]
    with torch.no_grad():
        w = first.weight.double() / torch.from_numpy(sx)[None, :]
        first.bias.copy_((first.bias.double() - w @ torch.from_numpy(mx)).float())
        first.weight.copy_(w.float())
        sy_t = torch.from_numpy(sy)
        last.weight.copy_((last.weight.double() * sy_t[:, None]).float())
        last.bias.copy_((last.bias.double() * sy_t + torch.from_numpy(my)).float())


@register("mlp")
class MLPRegressor(Regressor):
    """Forward: (B, D_in) raw inputs -> (B, D_out) raw outputs."""

    config_class = MLPConfig
    # dropout 0.2 and weight decay 1 helped most; the width hardly mattered (docs/regressors.md)
    search_grid = {"weight_decay": [1e-2, 1e-1, 1.0], "dropout": [0.0, 0.2], "hidden": [[128, 128], [256, 256]]}

    def __init__(self, d_in: int, d_out: int, config: MLPConfig, info: dict | None = None):
        super().__init__()
        self.config = config
        self.d_in, self.d_out = int(d_in), int(d_out)
        self.net = build_net(self.d_in, self.d_out, config)
        self.info = dict(info or {})

    @classmethod
    def fit(cls, x, y, config=None, x_val=None, y_val=None, seed=0):
        cfg = as_config(MLPConfig, config, "regressor mlp")
        if cfg.target_scaling not in ("global", "per_output"):
            raise FacesynthError(f"regressor mlp: target_scaling must be 'global' or 'per_output', got {cfg.target_scaling!r}")
        x, y = check_xy(x, y, "regressor mlp")
        if x_val is None or y_val is None:
            tr, va = tail_holdout(len(x), cfg.val_fraction)
            x, y, x_val, y_val = x[tr], y[tr], x[va], y[va]
        else:
            x_val, y_val = check_xy(x_val, y_val, "regressor mlp (validation slice)", min_rows=1)
        mx, sx = standardiser(x)
        my = y.mean(0)
        if cfg.target_scaling == "global":
            sy = np.full(y.shape[1], max(float(np.sqrt(((y - my) ** 2).mean())), 1e-12))
        else:
            sy = standardiser(y)[1]
        to_t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
        xt, yt = to_t((x - mx) / sx), to_t((y - my) / sy)
        xv, yv = to_t((x_val - mx) / sx), to_t((y_val - my) / sy)

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = cls(x.shape[1], y.shape[1], cfg)
            gen = torch.Generator().manual_seed(seed)
            opt = torch.optim.AdamW(model.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
            best, best_state, best_epoch, epoch = np.inf, None, -1, -1
            bs = max(1, int(cfg.batch_size))
            bar = progress_bar(total=int(cfg.max_epochs), desc="MLP epochs", unit="epoch")
            for epoch in range(int(cfg.max_epochs)):
                bar.update(1)
                model.net.train()
                perm = torch.randperm(len(xt), generator=gen)
                for start in range(0, len(xt), bs):
                    idx = perm[start : start + bs]
                    loss = torch.mean((model.net(xt[idx]) - yt[idx]) ** 2)
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                model.net.eval()
                with torch.no_grad():
                    val = float(torch.mean((model.net(xv) - yv) ** 2))
                if val < best:
                    best, best_epoch = val, epoch
                    best_state = copy.deepcopy(model.net.state_dict())
                elif epoch - best_epoch >= cfg.patience:
                    break
                bar.set_postfix(val=f"{val:.4f}", best_epoch=best_epoch + 1, refresh=False)
            bar.close()
        model.net.load_state_dict(best_state)
        _fold(model.net, mx, sx, my, sy)
        model.info = {"best_epoch": best_epoch + 1, "epochs_run": epoch + 1,
                      "val_mse_standardised": best}
        return model.eval()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def config_dict(self) -> dict:
        c = self.config
        return {
            "d_in": self.d_in, "d_out": self.d_out, "hidden": [int(h) for h in c.hidden],
            "activation": c.activation, "weight_decay": float(c.weight_decay), "lr": float(c.lr),
            "max_epochs": int(c.max_epochs), "patience": int(c.patience), "batch_size": int(c.batch_size),
            "dropout": float(c.dropout), "val_fraction": float(c.val_fraction),
            "target_scaling": c.target_scaling, "info": self.info,
        }

    @classmethod
    def from_state(cls, config, tensors):
        config = dict(config)
        d_in, d_out, info = config.pop("d_in"), config.pop("d_out"), config.pop("info", {})
        model = cls(d_in, d_out, as_config(MLPConfig, config, "regressor mlp"), info)
        model.load_state_dict(tensors)
        return model.eval()

    def summary(self) -> dict:
        n_params = sum(p.numel() for p in self.parameters())
        return {"n_parameters": int(n_params), **self.info}
