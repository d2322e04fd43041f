"""Fitting a shape-appearance dependence mapping (SADM) on a face model, and its artifact
(the run directory's part of it; the whole layout is :mod:`facesynth.rundir`)::

    RUN/face_model/         the face model artifact (facesynth.model.artifact)
    RUN/sadm/sadm.json      regressor name + hyper-parameters, SADM settings, provenance
    RUN/sadm/regressor.safetensors
      (with the gaze path's tensors under ``gaze.*`` when it has one: schemes with irises)

References
----------
The linear SADM (A = G S^T (S S^T)^-1) is Eq. 5 of the shape-appearance dependence paper
this project builds on; the other regressors replace that map.

One fit holds the regressor and what is chosen on held-out predictions of the same training
rows by refitting it on a part of them (the gaze path, the per-region shrinkage, the
restoration filter's strength), and the artifact round trip, hence its length.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from facesynth.artifact import manifest_field, read_manifest, read_tensors, rebuild, save_artifact
from facesynth.data.sequence import FaceSequence
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.model.artifact import load_face_model, save_face_model
from facesynth.model.artifact import read_manifest as face_model_manifest
from facesynth.model.face_model import FaceModel
from facesynth.model.restore import full_kernel, guard_restoration, validation_predictions
from facesynth.regressors import REGISTRY, Regressor, search
from facesynth.sadm.compress import compress_synthesizer
from facesynth.sadm.gaze import TARGETS as GAZE_TARGETS
from facesynth.sadm.gaze import GazeInputs, GazePath, eye_columns, fit_gaze_path, has_irises
from facesynth.sadm.regions import check_shrink, fit_region_shrink, shrink_appearance
from facesynth.sadm.synthesis import GlobalAppearance, ShapeEncoder, ShapeFeatures, Synthesizer

log = logging.getLogger(__name__)
SADM_FORMAT, SADM_FORMAT_VERSION = "facesynth.sadm", 1
SADM_TENSORS, SADM_MANIFEST = "regressor.safetensors", "sadm.json"
GAZE_PREFIX = "gaze."
GAZE_MODES = ("path", "inside", "both")
MIN_SHRINK_FRAMES = 10  # fewer validation frames than this: no per-region shrinkage


@dataclass
class SADMConfig:
    """How the mapping is trained (the Hydra ``sadm`` node).

    features : 'bs' (the paper), 'landmarks' (aligned coordinates), 'bs+landmarks', or
        'landmarks_rigid' (coordinates aligned on the eye corners and nose only)
    augment_sigma : std (frame pixels) of Gaussian noise added to copies of the
        training landmarks, targets unchanged: trains robustness to landmark noise;
        None = the regressor's own (``sadm_defaults``: 2 px, krr 1 px)
    augment_copies : number of noisy copies (0: no augmentation)
    search : grid-search the regressor's hyper-parameters on the validation slice
    val_fraction : the last fraction of the training segment used as validation
    clamp_shape : clamp b_s to +-k sqrt(lambda) before the regressor
    gaze : use gaze (facesynth.sadm.gaze): None = when the landmark scheme has irises
        (``ibug68+iris``, ``mediapipe478``); True on a scheme without irises is an error
    gaze_mode : 'path' (a ridge from the gaze features to the main regressor's residual,
        added to its prediction), 'inside' (the gaze features appended to the main
        regressor's inputs, ``gaze_copies`` times), or 'both'
    gaze_copies : repeats of the 4 gaze features among the main regressor's inputs ('inside', 'both')
    gaze_target : what the gaze path corrects: 'eyes' (the texture of the eye region, zero
        elsewhere) or 'params' (b_g: every pixel)
    gaze_folds : contiguous blocks of the training segment for the gaze path's cross-fitted
        residuals and its alpha (0: in-sample residuals, default alpha)
    region_shrink : shrink the prediction towards the mean texture per face part, by weights
        chosen on held-out training frames (:mod:`facesynth.sadm.regions`)
    shrink_folds : blocked cross-validation over this many contiguous blocks of the training
        segment, or (< 2) the validation slice (at least :data:`MIN_SHRINK_FRAMES` frames)
    restore_guard : with a face model holding a restoration filter (``model.restore=true``),
        the PSNR (dB) the filter may cost on held-out predictions of every validation slice
        (:func:`facesynth.model.restore.slice_stops`): the filter goes as far along its path (the
        mean texture's part first, then the variation's, up to ``model.restore_variation``) as costs
        no more (:func:`facesynth.model.restore.guard_restoration`);
        None (default) = the path's end (``model.restore_variation``); :data:`~facesynth.model.restore.GUARD_DB`
        (0.05) trades some of its LPIPS gain for PSNR (docs/studies/example-detail.md)
    """

    features: str = "landmarks"
    augment_sigma: Optional[float] = None
    augment_copies: int = 4
    search: bool = False
    val_fraction: float = 0.15
    clamp_shape: bool = True
    gaze: Optional[bool] = None
    gaze_mode: str = "both"
    gaze_copies: int = 4
    gaze_target: str = "eyes"
    gaze_folds: int = 5
    region_shrink: bool = True
    shrink_folds: int = 5
    restore_guard: Optional[float] = None  # GUARD_DB (0.05) caps the filter's PSNR cost; off: it costs mouth LPIPS and sharpness


@dataclass
class SADM:
    """A fitted mapping: ``regressor`` maps shape features to b_g of ``model``."""

    model: FaceModel
    regressor: Regressor
    name: str
    config: SADMConfig
    regressor_config: dict = field(default_factory=dict)
    search_table: list = field(default_factory=list)
    scheme: str = "ibug68"
    gaze: GazePath | None = None
    region_shrink: dict | None = None  # {"weights": {part: w}, "psnr": ..., "val_frames": n}; None: no shrinkage
    restore: dict | None = None  # the restoration filter's strength and its validation figures; None: not chosen

    def appearance(self) -> GlobalAppearance:
        app = GlobalAppearance(self.model, self.regressor, self.config.features, gaze=self.gaze,
                               gaze_inputs=gaze_inputs(self.config, get_scheme(self.scheme)))
        return app if self.region_shrink is None else shrink_appearance(app, self.model, self.region_shrink["weights"])

    def synthesizer(self) -> Synthesizer:
        """The whole landmarks -> face graph (eval mode); it takes (B, P, 2) landmarks of ``scheme``."""
        return Synthesizer(self.model, self.appearance(), self.config.clamp_shape, self.scheme).eval()

    def compressed(self, landmarks: np.ndarray, keep: int | None = None, predicted_variance: float | None = None):
        """The synthesizer with only the appearance components of largest predicted variance
        over ``landmarks`` (N, P, 2) (the training frames); the rest are folded into the
        mean. Returns ``(Synthesizer, info)``; see :func:`facesynth.sadm.compress.compress_synthesizer`."""
        return compress_synthesizer(self.synthesizer(), landmarks, keep, predicted_variance)

    def gaze_summary(self) -> dict | None:
        """How this SADM uses gaze (None: not at all): mode, gaze-input copies, the path's summary."""
        inputs = gaze_inputs(self.config, get_scheme(self.scheme))
        if inputs is None and self.gaze is None:
            return None
        return {"mode": self.config.gaze_mode, "input_copies": None if inputs is None else inputs.copies,
                "path": None if self.gaze is None else self.gaze.summary()}

    def features(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) frame landmarks -> (N, F) main-regressor inputs (gaze inputs included)."""
        return main_features(self.model, self.config, get_scheme(self.scheme), landmarks)

    def predict_params(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) -> predicted b_g (N, K_g), clamped (gaze path included)."""
        app = self.appearance().eval()
        enc = ShapeEncoder(self.model, self.config.clamp_shape)
        lm = torch.from_numpy(model_input(self.model, landmarks))
        with torch.no_grad():
            return app.params(*enc(lm[:, : self.model.mean_shape.shape[0]]), lm).numpy()


def gaze_inputs(cfg: SADMConfig, scheme) -> GazeInputs | None:
    """The main regressor's extra gaze inputs of ``cfg`` (None unless gaze is on in mode 'inside' / 'both')."""
    on = has_irises(scheme) if cfg.gaze is None else bool(cfg.gaze)
    return GazeInputs(scheme, cfg.gaze_copies) if on and cfg.gaze_mode in ("inside", "both") else None


def model_input(model: FaceModel, landmarks: np.ndarray) -> np.ndarray:
    """(N, P, 2) frame landmarks -> float32 (N, P, 2) with the face model's points denoised
    (:meth:`FaceModel.denoise`; the rest, e.g. irises beyond them, as given): what the
    synthesis graph reads (its ``denoise``, :class:`facesynth.model.denoise.ShapeDenoiser`)."""
    lm = np.array(landmarks, np.float32)
    n = model.mean_shape.shape[0]
    if model.denoise_pca is not None:
        lm[:, :n] = model.denoise(lm[:, :n])
    return lm


def main_features(model: FaceModel, cfg: SADMConfig, scheme, landmarks: np.ndarray) -> np.ndarray:
    """(N, P, 2) frame landmarks -> (N, F) float32 main-regressor inputs: the shape features of
    the model's points, then the gaze inputs (if any), of the :func:`model_input`."""
    lm = model_input(model, landmarks)
    x = ShapeFeatures.numpy(model, lm[:, : model.mean_shape.shape[0]], cfg.features, cfg.clamp_shape)
    extra = gaze_inputs(cfg, scheme)
    if extra is None:
        return x
    with torch.no_grad():
        return np.concatenate([x, extra(torch.from_numpy(lm)).numpy()], 1)


def make_config(name: str, params: dict):
    """The config dataclass of regressor ``name`` filled with ``params`` (its defaults elsewhere)."""
    try:
        return REGISTRY[name].config_class(**params)
    except TypeError as exc:
        raise FacesynthError(f"regressor '{name}': bad hyper-parameters {params}: {exc}") from None


def resolve_sadm_config(name: str, config: SADMConfig | None = None) -> SADMConfig:
    """``config`` (default ``SADMConfig()``) with its None fields set from regressor
    ``name``'s ``sadm_defaults``; FacesynthError for an unknown regressor."""
    if name not in REGISTRY:
        raise FacesynthError(f"unknown regressor '{name}' (available: {', '.join(sorted(REGISTRY))})")
    cfg = config or SADMConfig()
    return replace(cfg, **{k: v for k, v in REGISTRY[name].sadm_defaults.items() if getattr(cfg, k) is None})


def fit_sadm(
    model: FaceModel,
    seq: FaceSequence,
    rows: np.ndarray,
    textures: np.ndarray,
    name: str,
    params: dict | None = None,
    config: SADMConfig | None = None,
    seed: int = 0,
) -> SADM:
    """Fit the mapping on training ``rows`` of ``seq``.

    Parameters
    ----------
    textures : (len(rows), C * M) float32 training textures (as from model.sample_textures)
    name, params : regressor name in the registry and its hyper-parameters
    config : SADM settings (default ``SADMConfig()``); fields left None take the regressor's
        ``sadm_defaults`` (krr: 1 px augmentation), as in ``train.py regressor=NAME``
    """
    cfg = resolve_sadm_config(name, config)
    params = dict(params or {})
    rows = np.asarray(rows)
    scheme = get_scheme(seq.scheme)
    n_model = model.mean_shape.shape[0]
    if scheme.base_scheme().n_points != n_model:
        raise FacesynthError(f"{seq.name}: {scheme.name} landmarks do not fit a face model of {n_model} points "
                             f"(fit the face model on seq.to_scheme({scheme.base_scheme().name!r}))")
    use_gaze = has_irises(scheme) if cfg.gaze is None else bool(cfg.gaze)
    if use_gaze and not has_irises(scheme):
        raise FacesynthError(f"sadm.gaze=true needs a landmark scheme with irises; {seq.name} has {scheme.name}")
    if cfg.gaze_mode not in GAZE_MODES:
        raise FacesynthError(f"sadm.gaze_mode must be one of {GAZE_MODES}, got {cfg.gaze_mode!r}")
    if cfg.gaze_target not in GAZE_TARGETS:
        raise FacesynthError(f"sadm.gaze_target must be one of {GAZE_TARGETS}, got {cfg.gaze_target!r}")
    lm = seq.landmarks[rows]
    y = model.appearance_params(textures)

    def features(landmarks):
        return main_features(model, cfg, scheme, landmarks)

    n_val = validation_size(cfg, len(rows))
    fit_idx, val_idx = np.arange(len(rows) - n_val), np.arange(len(rows) - n_val, len(rows))
    rng = np.random.default_rng(seed)
    rng_extra = np.random.default_rng([seed, 1])  # noise on points beyond the model's: the model's own draws unchanged

    def noisy(idx):
        out = lm[idx] + 0  # a copy
        out[:, :n_model] += rng.normal(0, cfg.augment_sigma, out[:, :n_model].shape).astype(np.float32)
        if out.shape[1] > n_model:
            out[:, n_model:] += rng_extra.normal(0, cfg.augment_sigma, out[:, n_model:].shape).astype(np.float32)
        return out

    def design_landmarks(idx):
        """(landmarks of the design rows, their targets, their training-row positions)."""
        lms, ys = [lm[idx]], [y[idx]]
        for _ in range(cfg.augment_copies if cfg.augment_sigma > 0 else 0):
            lms.append(noisy(idx))
            ys.append(y[idx])
        return np.concatenate(lms), np.concatenate(ys), np.tile(idx, len(lms))

    def design(idx):
        lms, ys, _ = design_landmarks(idx)
        return features(lms), ys

    table: list = []
    if cfg.search:
        if n_val < 2:
            raise FacesynthError("search needs a validation slice: raise sadm.val_fraction")
        x_fit, y_fit = design(fit_idx)
        best, table = search(name, x_fit, y_fit, features(lm[val_idx]), y[val_idx],
                             REGISTRY[name].search_grid, make_config(name, params), seed)
        params = {**params, **(asdict(best) if hasattr(best, "__dataclass_fields__") else dict(best))}
        log.info("search for %s picked %s", name, params)
    lm_all, yy, pos = design_landmarks(np.arange(len(rows)))
    x = features(lm_all)
    torch.manual_seed(seed)
    x_val = features(lm[val_idx]) if n_val else None
    reg = REGISTRY[name].fit(x, yy, make_config(name, params), x_val, y[val_idx] if n_val else None, seed=seed)
    gaze = None
    if use_gaze and cfg.gaze_mode in ("path", "both"):
        gaze = _fit_gaze(model, cfg, scheme, name, params, reg.eval(), x, yy, model_input(model, lm_all), pos, len(rows), seed)
        log.info("gaze path: alpha %g", gaze.alpha)
    refit = refitter(model, seq, rows, textures, name, params, cfg, seed)
    shrink = None
    if cfg.region_shrink and (cfg.shrink_folds >= 2 or n_val >= MIN_SHRINK_FRAMES):
        shrink = fit_region_shrink(refit, model, lm, textures, cfg.shrink_folds, n_val)
        log.info("region shrinkage: %s", shrink["weights"])
    restore = None
    if full_kernel(model) is not None and cfg.restore_guard is not None and n_val >= 2 and seq.has_frames:
        restore = guard_restoration(refit, model, seq, rows, n_val, cfg.restore_guard)
        log.info("restoration filter: mean %g, variation %g (validation PSNR %+.3f dB)", restore["mean_strength"],
                 restore["strength"], restore["psnr_change_db"])
    return SADM(model, reg.eval(), name, cfg, reg.config_dict(), table, scheme.name, gaze, shrink, restore)


def validation_size(cfg: SADMConfig, n_rows: int) -> int:
    """The validation slice's length (rows at the end of the training rows) under ``cfg.val_fraction``."""
    return int(round(n_rows * cfg.val_fraction))


def refitter(model: FaceModel, seq: FaceSequence, rows: np.ndarray, textures: np.ndarray, name: str, params: dict,
             cfg: SADMConfig, seed: int = 0):
    """``fit(i)``: the synthesiser of the mapping fitted on ``rows[i]`` alone (``textures[i]``), for
    held-out predictions of the other rows: ``cfg`` without the search, the per-region shrinkage
    and the filter's guard, the gaze path on in-sample residuals."""
    probe = replace(cfg, region_shrink=False, search=False, gaze_folds=0, restore_guard=None)
    rows = np.asarray(rows)

    def fit(i):
        return fit_sadm(model, seq, rows[i], textures[i], name, params, probe, seed).synthesizer()

    return fit


def held_out_predictions(model: FaceModel, seq: FaceSequence, rows: np.ndarray, textures: np.ndarray, name: str,
                         params: dict | None = None, config: SADMConfig | None = None, seed: int = 0,
                         n_val: int | None = None):
    """``(before, val, pred)`` of :func:`facesynth.model.restore.validation_predictions` for the
    mapping ``fit_sadm(model, seq, rows, textures, name, params, config, seed)`` would fit: its
    validation slice (the last ``n_val`` of ``rows``; default :func:`validation_size`) predicted
    by the mapping refitted (:func:`refitter`) on the rows before the slice and a gap as long as
    it (``textures``: of those rows at least)."""
    cfg = resolve_sadm_config(name, config)
    fit = refitter(model, seq, rows, textures, name, dict(params or {}), cfg, seed)
    return validation_predictions(fit, seq, rows, validation_size(cfg, len(rows)) if n_val is None else n_val)


def _predict(reg, x: np.ndarray, batch: int = 4096) -> np.ndarray:
    with torch.no_grad():
        return np.concatenate([reg(torch.from_numpy(x[i:i + batch])).double().numpy() for i in range(0, len(x), batch)])


def _fit_gaze(model, cfg, scheme, name, params, reg, x, y, lm, pos, n_rows, seed) -> GazePath:
    """The gaze path on the main regressor's residuals: cross-fitted over ``folds``
    contiguous blocks of the ``n_rows`` training frames (``pos``: each design row's frame),
    or in-sample when ``folds`` < 2 (see facesynth.sadm.gaze)."""
    folds = cfg.gaze_folds
    if folds >= 2:
        groups = np.minimum(pos * folds // n_rows, folds - 1)
        pred = np.empty_like(y, dtype=np.float64)
        for f in range(folds):
            out = groups == f
            torch.manual_seed(seed)
            part = REGISTRY[name].fit(x[~out], y[~out], make_config(name, params), None, None, seed=seed).eval()
            pred[out] = _predict(part, x[out])
    else:
        groups, pred = np.zeros(len(y), np.int64), _predict(reg, x)
    if cfg.gaze_target == "params":
        return fit_gaze_path(scheme, lm, y - pred, groups)
    cols = eye_columns(model, scheme.base_scheme())
    res = (y - pred) @ model.appearance_pca.components[:, cols].astype(np.float64)  # the residual's texture there
    return fit_gaze_path(scheme, lm, res, groups, columns=cols, n_out=model.appearance_pca.components.shape[1],
                         target=cfg.gaze_target)


def save_sadm(sadm: SADM, run_dir: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write the face model (``run_dir/face_model/``) and the mapping (``run_dir/sadm/``:
    ``sadm.json`` + ``regressor.safetensors``), atomic per file."""
    d = Path(run_dir)
    save_face_model(sadm.model, d / "face_model")
    tensors = {k: v.detach().contiguous().numpy() for k, v in sadm.regressor.state_dict().items()}
    if sadm.gaze is not None:
        tensors.update({GAZE_PREFIX + k: v.detach().contiguous().numpy() for k, v in sadm.gaze.state_dict().items()})
    save_artifact(d / "sadm", SADM_TENSORS, SADM_MANIFEST, tensors, {
        "regressor": sadm.name,
        "landmark_scheme": sadm.scheme,  # the input's; the face model's is its base (ibug68+iris -> ibug68)
        "gaze": None if sadm.gaze is None else sadm.gaze.summary(),  # the path's tensors: gaze.* (None: no path)
        "gaze_use": sadm.gaze_summary(),
        "regressor_config": sadm.regressor_config,
        "regressor_summary": sadm.regressor.summary(),
        "sadm": asdict(sadm.config),
        "search_table": sadm.search_table,
        "region_shrink": sadm.region_shrink,  # per-part weights towards the mean texture (None: none)
        "restore": sadm.restore,  # the filter's point on its path: path, mean_strength, strength (the variation's); None: not chosen
        "data_fingerprint": sadm.model.fingerprint,
        "face_model_sha256": face_model_manifest(d / "face_model")["tensors_sha256"],
        **(extra or {}),
    }, SADM_FORMAT, SADM_FORMAT_VERSION)
    return d


def load_sadm(run_dir: str | os.PathLike) -> SADM:
    """Load a run written by :func:`save_sadm` (or by ``train.py``).

    Every failure (missing, truncated, altered or non-finite files, invalid JSON, missing
    fields, tensors that do not fit the regressor or the face model) is a FacesynthError
    naming the file. The SADM manifest is written last and records the face model's
    tensors' SHA-256, so a face model from another save is refused.
    """
    d = Path(run_dir)
    if not (d / "sadm" / SADM_MANIFEST).is_file():
        raise FacesynthError(f"{d}: not a training run (sadm/{SADM_MANIFEST} missing)")
    meta = read_manifest(d / "sadm", SADM_MANIFEST, SADM_FORMAT, SADM_FORMAT_VERSION, "SADM")
    where = d / "sadm" / SADM_MANIFEST
    name = manifest_field(meta, "regressor", where)
    if not isinstance(name, str) or name not in REGISTRY:
        raise FacesynthError(f"{where}: regressor {name!r} is not available in this build")
    model = load_face_model(d / "face_model")
    paired = meta.get("face_model_sha256")
    if paired is not None and paired != face_model_manifest(d / "face_model").get("tensors_sha256"):
        raise FacesynthError(f"{d / 'face_model'}: not the face model this SADM was saved with "
                             f"(its SHA-256 differs from {where}'s 'face_model_sha256')")
    try:
        scheme = get_scheme(manifest_field(meta, "landmark_scheme", where))
    except FacesynthError as exc:
        raise FacesynthError(f"{where}: {exc}") from None
    if scheme.base_scheme().name != model.scheme:
        raise FacesynthError(f"{where}: landmark scheme {scheme.name!r} needs a face model in "
                             f"{scheme.base_scheme().name!r}, but the one in {d / 'face_model'} has {model.scheme!r}")
    tensors = read_tensors(d / "sadm", SADM_TENSORS, meta, "SADM regressor")
    conf = manifest_field(meta, "regressor_config", where)
    sadm_conf = manifest_field(meta, "sadm", where)

    gaze_meta = manifest_field(meta, "gaze", where)  # None: no gaze path

    def build() -> SADM:
        reg = REGISTRY[name].from_state(conf, {k: torch.from_numpy(v) for k, v in tensors.items()
                                               if not k.startswith(GAZE_PREFIX)})
        gaze = None
        if gaze_meta is not None:
            state = {k[len(GAZE_PREFIX):]: torch.from_numpy(v) for k, v in tensors.items() if k.startswith(GAZE_PREFIX)}
            gaze = GazePath.from_state(scheme, state, float(manifest_field(gaze_meta, "alpha", where)),
                                       str(manifest_field(gaze_meta, "target", where))).eval()
        cfg = SADMConfig(**{k: v for k, v in dict(sadm_conf).items() if k in SADMConfig.__dataclass_fields__})
        sadm = SADM(model, reg.eval(), name, cfg, conf, meta.get("search_table", []), scheme.name, gaze,
                    check_shrink(meta.get("region_shrink"), where), meta.get("restore"))
        _smoke_test(sadm)
        return sadm

    return rebuild(d / "sadm" / SADM_TENSORS, f"SADM regressor {name!r}", build)


def _smoke_test(sadm: SADM) -> None:
    """One forward pass on the reference shape: tensors that do not fit the face model
    raise here (RuntimeError), not at first use; non-finite outputs raise ValueError."""
    lm = np.ascontiguousarray(sadm.model.reference.points, np.float32)
    extra = get_scheme(sadm.scheme).n_points - len(lm)
    if extra > 0:  # e.g. irises: put them at the model points' centroid (a finite input is all this needs)
        lm = np.concatenate([lm, np.repeat(lm.mean(0, keepdims=True), extra, 0)])
    sch = get_scheme(sadm.scheme)
    if has_irises(sch):  # the gaze features need each iris off its eye's corners: at the reference's eye centres
        corners, centres = sch.region("eye_corners"), sch.region("iris_centres")
        lm[centres] = 0.5 * (lm[corners[[0, 2]]] + lm[corners[[1, 3]]])
    lm = torch.from_numpy(lm[None])
    with torch.no_grad():
        outs = sadm.synthesizer()(lm)
    for out in outs if isinstance(outs, (tuple, list)) else (outs,):
        if not torch.isfinite(out).all():
            raise ValueError("the synthesizer's output on the reference shape is not finite")
