"""Structured configuration of the ERI model (the Hydra ``eri/`` group fills it).

Every knob of training, the ratio images, the eigenERI PCA, the SVR driving model and
synthesis lives here, with its default; ``conf/eri/default.yaml`` only selects it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from facesynth.errors import FacesynthError

SVR_VARIANTS = ("eps_linear", "eps_rbf", "nu_linear", "nu_rbf")


@dataclass
class EriConfig:
    """Settings of :func:`facesynth.eri.train.train_eri` and :class:`EriModel`.

    Neutral frame
        ``neutral_index``: a training row, or ``None`` for automatic selection (the frame
        closest to the mean shape among frames whose mouth is closed,
        ``mouth_closed_max`` = inner-lip gap / inter-ocular distance).
    Geometry
        ``width``/``margin``: pixel scale of the model geometry (the neutral shape);
        ``forehead``: height (fraction of the eye-to-chin distance) of 10 extra points
        above the brows that move rigidly with the head, so forehead wrinkles enter
        the ratio image (0 disables them); ``mouth_gap``: inner lips of the model
        geometry opened by this fraction of the inter-ocular distance so that the
        mouth interior has pixels (0 = exactly the neutral frame's geometry).
    Ratio images (Liu et al. 2001)
        ``eps`` added to numerator and denominator (intensities in [0, 1]);
        ratios clipped to ``[1/clip, clip]``; ``sigma`` of the Gaussian filter applied
        to the ratio image (pixels of the model geometry, 0 = none); ``log`` stores
        log ratios (PCA in the log domain) instead of plain ratios; ``edge_tau``: at
        synthesis, ratios are pulled towards 1 where the model's neutral texture has
        strong edges (confidence 1 / (1 + (|grad F_0| / edge_tau)^2); 0 = off), and
        brightening is capped at ``max_brighten`` (see ``ratio.to_multiplier``).
    eigenERI
        ``variance`` kept by the PCA (0.97 as in the paper) or ``n_components``.
    Driving model
        ``driver``: which SVR variant synthesis uses (one of ``SVR_VARIANTS``) or
        ``"auto"`` (lowest validation MSE); ``C``, ``epsilon`` (epsilon-SVR, in units of
        each coefficient's standard deviation), ``nu`` (nu-SVR), ``gamma`` (RBF; "scale"
        or a float); ``grid_search`` tries ``C_grid`` x ``gamma_grid`` on the validation
        slice (the last ``val_fraction`` of the training segment); ``compare`` lists SADM
        regressors (REGISTRY names) evaluated beside the SVRs (missing ones are skipped).
    Synthesis
        ``clamp_k`` limits predicted coefficients to +-k sqrt(eigenvalue);
        ``span_safety`` sizes the warp's candidate blocks; ``feather`` is the
        compositing edge width (frame pixels); ``batch_size`` frames per batch.
    Evaluation
        ``eval_frames`` caps the number of test frames rendered for the PSNR figures
        (0 = all); the temporal split is the run's (``data.train_fraction``, ``data.gap``).
    """

    neutral_index: int | None = None
    mouth_closed_max: float = 0.03
    width: int = 160
    margin: float = 0.1
    forehead: float = 0.25
    mouth_gap: float = 0.08
    eps: float = 0.02
    clip: float = 4.0
    sigma: float = 1.0
    log: bool = True
    edge_tau: float = 0.03
    max_brighten: float = 1.15
    variance: float = 0.97
    n_components: int | None = None
    driver: str = "auto"
    C: float = 1.0
    epsilon: float = 0.1
    nu: float = 0.5
    gamma: Any = "scale"
    grid_search: bool = False
    C_grid: list = field(default_factory=lambda: [0.1, 1.0, 10.0])
    gamma_grid: list = field(default_factory=lambda: [0.3, 1.0, 3.0])
    val_fraction: float = 0.15
    compare: list = field(default_factory=lambda: ["linear", "mlp"])
    clamp_k: float = 3.0
    span_safety: float = 1.5
    feather: float = 3.0
    batch_size: int = 32
    eval_frames: int = 0

    def __post_init__(self):
        if self.driver != "auto" and self.driver not in SVR_VARIANTS:
            raise FacesynthError(f"eri.driver must be 'auto' or one of {SVR_VARIANTS}, got {self.driver!r}")
        if not 0 < self.variance <= 1:
            raise FacesynthError(f"eri.variance must be in (0, 1], got {self.variance}")
        if self.eps <= 0 or self.clip <= 1:
            raise FacesynthError(f"eri.eps must be > 0 and eri.clip > 1, got {self.eps}, {self.clip}")
        if not 0 < self.val_fraction < 0.5:
            raise FacesynthError(f"eri.val_fraction must be in (0, 0.5), got {self.val_fraction}")
        if self.forehead < 0 or self.mouth_gap < 0 or self.sigma < 0:
            raise FacesynthError("eri.forehead, eri.mouth_gap and eri.sigma must be >= 0")

    @classmethod
    def from_dict(cls, d: Mapping | "EriConfig" | None) -> "EriConfig":
        """Build from a dict or an OmegaConf node; unknown keys are an error naming them."""
        if d is None:
            return cls()
        if isinstance(d, cls):
            return d
        if isinstance(d, DictConfig):
            d = OmegaConf.to_container(d, resolve=True)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise FacesynthError(f"eri config: unknown keys {unknown}; known keys are {sorted(known)}")
        return cls(**{k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()})

    def to_dict(self) -> dict:
        return asdict(self)
