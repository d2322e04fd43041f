"""Regressors from shape features to appearance parameters, shared by SADM and ERI: one
interface (fit on numpy, predict as ``torch.nn.Module``) and one registry.

Registered: ``linear`` (the paper's Eq. 5, with a ridge), ``poly2`` (quadratic features
+ ridge), ``mlp`` (torch MLP, early stopping), ``svr`` (scikit-learn SVR/NuSVR per output,
exact torch kernel expansion), ``krr`` (Matern/RBF kernel ridge blended with linear
ridge, exact torch kernel expansion).

``REGISTRY`` maps a name to its class; the class carries its config dataclass
(``config_class``, whose defaults are what ``train.py regressor=NAME`` trains with), its
SADM settings (``sadm_defaults``) and its search grid (``search_grid``). Every module of
this package is imported here, so a new regressor is one module with a ``@register``ed
class plus one ``conf/regressor/NAME.yaml`` that selects it (docs/architecture.md).
"""

import importlib
import pkgutil

from facesynth.regressors.base import REGISTRY, Regressor, register
from facesynth.regressors.krr import KRRConfig, KRRRegressor
from facesynth.regressors.linear import LinearConfig, LinearRegressor
from facesynth.regressors.mlp import MLPConfig, MLPRegressor
from facesynth.regressors.poly2 import Poly2Config, Poly2Regressor
from facesynth.regressors.search import search
from facesynth.regressors.svr import SVRConfig, SVRRegressor

for _module in pkgutil.iter_modules(__path__):  # registers every regressor module's classes
    importlib.import_module(f"{__name__}.{_module.name}")

CONFIGS = {name: cls.config_class for name, cls in REGISTRY.items()}  # a view of REGISTRY
DEFAULT_GRIDS = {name: cls.search_grid for name, cls in REGISTRY.items()}  # a view of REGISTRY

__all__ = [
    "CONFIGS", "DEFAULT_GRIDS", "KRRConfig", "KRRRegressor", "REGISTRY", "LinearConfig", "LinearRegressor", "MLPConfig",
    "MLPRegressor", "Poly2Config", "Poly2Regressor", "Regressor", "SVRConfig", "SVRRegressor", "register", "search",
]
