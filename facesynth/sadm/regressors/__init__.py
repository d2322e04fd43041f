"""SADM regressors: one interface (fit on numpy, predict as torch.nn.Module)."""

from facesynth.sadm.regressors.base import REGISTRY, Regressor, register
from facesynth.sadm.regressors.linear import LinearConfig, LinearRegressor

__all__ = ["REGISTRY", "LinearConfig", "LinearRegressor", "Regressor", "register"]
