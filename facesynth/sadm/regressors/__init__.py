"""SADM regressors: one interface (fit on numpy, predict as torch.nn.Module).

Registered: ``linear`` (the paper's Eq. 5, optional ridge), ``poly2`` (quadratic features
+ ridge), ``mlp`` (torch MLP, early stopping), ``svr`` (scikit-learn SVR/NuSVR per output,
exact torch kernel expansion), ``krr`` (RBF kernel ridge blended with linear
ridge, exact torch kernel expansion). ``CONFIGS`` maps each name to its config dataclass (for
Hydra's ConfigStore); :func:`search` grid-searches on a validation slice.
"""

from facesynth.sadm.regressors.base import REGISTRY, Regressor, register
from facesynth.sadm.regressors.krr import KRRConfig, KRRRegressor
from facesynth.sadm.regressors.linear import LinearConfig, LinearRegressor
from facesynth.sadm.regressors.mlp import MLPConfig, MLPRegressor
from facesynth.sadm.regressors.poly2 import Poly2Config, Poly2Regressor
from facesynth.sadm.regressors.search import DEFAULT_GRIDS, search
from facesynth.sadm.regressors.svr import SVRConfig, SVRRegressor

CONFIGS = {"linear": LinearConfig, "poly2": Poly2Config, "mlp": MLPConfig, "svr": SVRConfig, "krr": KRRConfig}

__all__ = [
    "CONFIGS", "DEFAULT_GRIDS", "KRRConfig", "KRRRegressor", "REGISTRY", "LinearConfig", "LinearRegressor", "MLPConfig", "MLPRegressor",
    "Poly2Config", "Poly2Regressor", "Regressor", "SVRConfig", "SVRRegressor", "register", "search",
]
