"""The regressor interface shared by every SADM regressor (and reused by ERI).

A regressor is *fitted* by a classmethod on numpy arrays and *predicts* as a
``torch.nn.Module``, so that batching and ONNX export are uniform::

    reg = REGISTRY["linear"].fit(x_train, y_train, cfg)         # (N, D_in), (N, D_out)
    y = reg(torch.from_numpy(x))                                # (B, D_in) -> (B, D_out)

Saving is ``reg.config_dict()`` (JSON) + ``reg.state_dict()`` (tensors);
loading is ``REGISTRY[name].from_state(config, tensors)``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

REGISTRY: dict[str, type["Regressor"]] = {}


def register(name: str):
    """Class decorator: register a regressor under ``name``."""

    def deco(cls):
        cls.name = name
        REGISTRY[name] = cls
        return cls

    return deco


class Regressor(nn.Module):
    """Base class. Subclasses implement ``fit``, ``forward``, ``config_dict``, ``from_state``."""

    name: ClassVar[str] = "base"
    config_class: ClassVar[type]  # the hyper-parameter dataclass: its defaults are train.py's
    # SADM settings this regressor trains with where the SADM config leaves them None
    # (fields of facesynth.sadm.fit.SADMConfig)
    sadm_defaults: ClassVar[dict[str, Any]] = {"augment_sigma": 2.0}
    # hyper-parameter grid of facesynth.regressors.search (``sadm.search=true``)
    search_grid: ClassVar[dict[str, list]] = {}

    @classmethod
    def fit(
        cls,
        x: np.ndarray,
        y: np.ndarray,
        config: Any = None,
        x_val: np.ndarray | None = None,
        y_val: np.ndarray | None = None,
        seed: int = 0,
    ) -> "Regressor":
        """Fit on (N, D_in) inputs and (N, D_out) targets (float); optional validation
        slice for early stopping / hyper-parameter search (never the test frames)."""
        raise NotImplementedError

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, D_in) -> (B, D_out)
        raise NotImplementedError

    def predict(self, x: np.ndarray) -> np.ndarray:
        """numpy convenience: (N, D_in) -> (N, D_out) float32."""
        with torch.no_grad():
            return self(torch.from_numpy(np.asarray(x, np.float32))).numpy()

    def config_dict(self) -> dict:
        """JSON-serialisable hyper-parameters and sizes needed by :meth:`from_state`."""
        raise NotImplementedError

    @classmethod
    def from_state(cls, config: dict, tensors: dict[str, torch.Tensor]) -> "Regressor":
        """Rebuild from :meth:`config_dict` and ``state_dict()`` tensors."""
        raise NotImplementedError

    def summary(self) -> dict:
        """Figures for reports (e.g. number of support vectors)."""
        return {}
