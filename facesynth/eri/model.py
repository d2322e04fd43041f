"""``EriModel``: one subject's expression ratio images, their PCA ("eigenERI") and the
SVR driving model from MPEG-4 FAPs, with saving/loading (safetensors + JSON manifest).

References
----------
Z. Liu, Y. Shan, Z. Zhang, "Expressive expression mapping with ratio images", SIGGRAPH 2001.
The FAP-driven eigenERI + SVR model follows the issue's paper (Fig. 5: epsilon/nu-SVR with
linear and RBF kernels predicting eigenERI coefficients from FAPs).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from facesynth.artifact import manifest_field, read_manifest, read_tensors, rebuild, save_artifact
from facesynth.data.sequence import FaceSequence
from facesynth.eri.config import SVR_VARIANTS, EriConfig
from facesynth.eri.driving import SVRBank, choose_driver, fit_variant
from facesynth.eri.faps import FAP_NAMES, compute_faps, fapu
from facesynth.eri.geometry import extend, forehead_points, open_mouth, select_neutral, to_canvas, upright
from facesynth.eri.ratio import ratio_images, sample_textures
from facesynth.errors import FacesynthError
from facesynth.model.artifact import check_pca, check_reference, check_size
from facesynth.model.pca import PCAModel
from facesynth.model.reference import ReferenceFrame
from facesynth.model.warp import ToReference, candidate_spans
from facesynth.progress import bar as progress_bar
from facesynth.progress import stage

log = logging.getLogger(__name__)

FORMAT, FORMAT_VERSION = "facesynth.eri_model", 1
TENSORS, MANIFEST = "eri_model.safetensors", "eri_model.json"


@dataclass
class EriModel:
    """Attributes
    ----------
    config : EriConfig
    neutral_index : int
        Sequence row of the neutral frame.
    neutral_landmarks : float32 (68, 2), the neutral frame's landmarks (frame pixels).
    forehead : float32 (F, 2), the neutral frame's forehead points (F = 0 or 10).
    reference : ReferenceFrame
        The model geometry: the neutral face (plus forehead, mouth opened by
        ``config.mouth_gap``), upright, ``config.width`` pixels wide.
    span : int64 (T, 2), candidate blocks of the warp to targets.
    neutral_texture : float32 (3, M), the neutral frame F_0 in the model geometry.
    pca : PCAModel over (3 * M,) ratio values (log R when ``config.log``).
    regressors : dict variant -> SVRBank (FAPs (B, 36) -> coefficients (B, K)).
    driver : str, the variant synthesis uses.
    """

    config: EriConfig
    neutral_index: int
    neutral_landmarks: np.ndarray
    forehead: np.ndarray
    reference: ReferenceFrame
    span: np.ndarray
    neutral_texture: np.ndarray
    pca: PCAModel
    regressors: dict = field(default_factory=dict)
    driver: str = "nu_rbf"
    fingerprint: str = ""
    meta: dict = field(default_factory=dict)
    training: dict | None = field(default=None, repr=False)  # faps/coefficients of the fit (not saved)

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, seq: FaceSequence, rows=None, config: EriConfig | None = None, progress: bool = False) -> "EriModel":
        """Fit on sequence ``rows`` (default all): neutral frame, ratio images, eigenERI, SVRs.

        The last ``config.val_fraction`` of ``rows`` is the validation slice for choosing
        the driver (``driver="auto"``) and the grid search; final regressors use all rows.
        """
        cfg = EriConfig.from_dict(config)
        seq.require_scheme("ibug68", "ERI")
        rows = np.arange(len(seq)) if rows is None else np.asarray(rows)
        if len(rows) < 10:
            raise FacesynthError(f"{seq.name}: ERI training needs at least 10 frames, got {len(rows)}")
        t0 = time.perf_counter()
        info: dict = {}
        if cfg.neutral_index is None:
            i, info = select_neutral(seq.landmarks[rows], cfg.mouth_closed_max)
            neutral_index = int(rows[i])
        else:
            neutral_index = int(cfg.neutral_index)
            if not 0 <= neutral_index < len(seq):
                raise FacesynthError(f"eri.neutral_index={neutral_index} is outside the sequence (0..{len(seq) - 1})")
            info = {"rule": "config"}
        model = cls.from_neutral(seq.landmarks[neutral_index], seq.frame(neutral_index), cfg)
        model.neutral_index, model.fingerprint = neutral_index, seq.fingerprint
        values = model.ratios_of(seq, rows, progress)
        t1 = time.perf_counter()
        pca = PCAModel.fit(values.reshape(len(rows), -1), cfg.n_components, cfg.variance)
        # the eigenERI basis is stored in half precision (docs/eri.md: tens of MB in float32 on a
        # real clip); rounding it here keeps the fitted and the reloaded model identical
        model.pca = PCAModel(pca.mean, pca.components.astype(np.float16).astype(np.float32), pca.eigenvalues,
                             pca.total_variance)
        coeffs = model.pca.project(values.reshape(len(rows), -1))
        del values
        faps = compute_faps(seq.landmarks[rows], model.neutral_landmarks)
        t2 = time.perf_counter()
        model.fit_regressors(faps, coeffs)
        model.training = {"rows": rows, "faps": faps, "coefficients": coeffs}
        canvas = to_canvas(model.extend(seq.landmarks[rows]), model.reference.points)[0]
        model.span = candidate_spans(model.reference, canvas, cfg.span_safety)
        t3 = time.perf_counter()
        model.meta.update({
            "sequence": seq.name, "train_frames": int(len(rows)), "neutral": {"row": neutral_index, **info},
            "n_components": model.pca.n_components, "variance_kept": model.pca.explained_variance_ratio,
            "fit_seconds": {"ratios": t1 - t0, "pca": t2 - t1, "regressors": t3 - t2},
        })
        log.info("eri: neutral row %d, %d eigenERIs (%.1f%% variance), driver %s", neutral_index,
                 model.pca.n_components, 100 * model.pca.explained_variance_ratio, model.driver)
        return model

    @classmethod
    def from_neutral(cls, neutral: np.ndarray, image: np.ndarray, cfg: EriConfig) -> "EriModel":
        """The geometry part of a model (no PCA/regressors yet) from a neutral face."""
        neutral = np.asarray(neutral, np.float32)
        fapu(neutral)  # validates the neutral face (raises on degenerate FAPUs)
        fh = forehead_points(neutral, cfg.forehead) if cfg.forehead > 0 else np.zeros((0, 2))
        pts = upright(open_mouth(extend(neutral, neutral, fh)[0], cfg.mouth_gap))
        ref = ReferenceFrame.from_mean_shape(pts, cfg.width, cfg.margin)
        model = cls(cfg, -1, neutral, fh.astype(np.float32), ref, np.zeros((ref.n_triangles, 2), np.int64),
                    np.zeros(0, np.float32), None)  # type: ignore[arg-type]
        model.neutral_texture = model.textures(image[None], neutral[None])[0].numpy()
        return model

    def fit_regressors(self, faps: np.ndarray, coeffs: np.ndarray) -> dict:
        """Fit every SVR variant; choose ``driver`` (config or lowest validation MSE)."""
        cfg = self.config
        n_val = max(1, int(round(len(faps) * cfg.val_fraction)))
        xt, yt, xv, yv = faps[:-n_val], coeffs[:-n_val], faps[-n_val:], coeffs[-n_val:]
        scale = coeffs.std(0) + 1e-12
        report = {}
        for v in SVR_VARIANTS:
            with stage(f"ERI driving model {v}") as st:
                bank, rep = fit_variant(v, xt, yt, cfg, xv, yv)
                if rep["val_mse"] is None:
                    rep["val_mse"] = float((((bank.predict(xv) - yv) / scale) ** 2).mean())
                    bank = SVRBank.fit(faps, coeffs, rep["params"])
                st.set(f"validation MSE {rep['val_mse']:.3f}")
            self.regressors[v] = bank
            report[v] = {**rep, "support_vectors": int(len(bank.sv))}
        if cfg.driver != "auto":
            self.driver, rule = cfg.driver, "config"
        else:
            self.driver, rule = choose_driver(report)
        self.meta["regressors"] = report
        self.meta["driver_choice"] = {"driver": self.driver, "rule": rule}
        return report

    # ------------------------------------------------------------- utilities
    def sampler(self) -> ToReference:
        if "_sampler" not in self.__dict__:
            self.__dict__["_sampler"] = ToReference(self.reference)
        return self.__dict__["_sampler"]

    @property
    def n_pixels(self) -> int:
        return self.sampler().n_pixels

    def extend(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, 68, 2) frames of the training subject -> (N, P, 2) with forehead points."""
        return extend(landmarks, self.neutral_landmarks, self.forehead)

    def textures(self, images: np.ndarray, landmarks: np.ndarray) -> torch.Tensor:
        """uint8 (B, H, W, 3) + (B, 68, 2) of the training subject -> (B, 3, M) in the model geometry."""
        return sample_textures(images, self.extend(landmarks), self.sampler())

    def ratios_of(self, seq: FaceSequence, rows, progress: bool = False) -> np.ndarray:
        """Ratio values (log R or R) of sequence rows: float32 (N, 3, M)."""
        cfg, rows = self.config, np.asarray(rows)
        out = np.empty((len(rows), 3, self.n_pixels), np.float32)
        neutral = torch.from_numpy(self.neutral_texture)
        frames = seq.iter_frames(rows)
        for s in progress_bar(range(0, len(rows), cfg.batch_size), desc="ratio images", unit="batch", enabled=progress):
            chunk = rows[s : s + cfg.batch_size]
            tex = self.textures(np.stack([next(frames) for _ in chunk]), seq.landmarks[chunk])
            out[s : s + len(chunk)] = ratio_images(tex, neutral, self.sampler(), cfg.eps, cfg.clip, cfg.sigma, cfg.log).numpy()
        return out

    def faps(self, landmarks: np.ndarray) -> np.ndarray:
        """FAPs (N, 36) of the training subject's frames, relative to the model's neutral."""
        return compute_faps(landmarks, self.neutral_landmarks)

    def predict_coefficients(self, faps: np.ndarray, variant: str | None = None, clamp: bool = True) -> np.ndarray:
        """(N, 36) FAPs -> (N, K) eigenERI coefficients (clamped to +-clamp_k sqrt(lambda))."""
        v = variant or self.driver
        if v not in self.regressors:
            raise FacesynthError(f"ERI model has no regressor {v!r}; it has {sorted(self.regressors)}")
        b = self.regressors[v].predict(np.asarray(faps, np.float32))
        return self.pca.clamp(b, self.config.clamp_k) if clamp else b

    def describe(self) -> dict:
        return {"neutral_index": self.neutral_index, "n_components": self.pca.n_components,
                "variance_kept": self.pca.explained_variance_ratio, "n_pixels": self.n_pixels,
                "reference_size": list(self.reference.size), "driver": self.driver, "n_faps": len(FAP_NAMES),
                "driver_choice": self.meta.get("driver_choice", {})}

    # ------------------------------------------------------------ save / load
    def save(self, directory: str | os.PathLike, extra: dict | None = None) -> Path:
        """Write ``eri_model.safetensors`` + ``eri_model.json`` into ``directory`` (atomically)."""
        t = {"neutral_landmarks": self.neutral_landmarks, "forehead": np.asarray(self.forehead, np.float32),
             "reference_points": self.reference.points, "triangles": self.reference.triangles.astype(np.int64),
             "span": self.span.astype(np.int64), "neutral_texture": self.neutral_texture,
             "pca_mean": self.pca.mean, "pca_components": self.pca.components.astype(np.float16),
             "pca_eigenvalues": self.pca.eigenvalues.astype(np.float64)}
        regs = {}
        for name, reg in self.regressors.items():
            regs[name] = reg.config_dict()
            t.update({f"reg.{name}.{k}": v for k, v in _compact_bank_state(reg).items()})
        return save_artifact(directory, TENSORS, MANIFEST, t, {
            "config": self.config.to_dict(), "neutral_index": self.neutral_index,
            "reference_size": list(self.reference.size), "pca_total_variance": self.pca.total_variance,
            "driver": self.driver, "regressors": regs, "fap_names": list(FAP_NAMES), "data_fingerprint": self.fingerprint,
            "meta": self.meta, **(extra or {}),
        }, FORMAT, FORMAT_VERSION)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "EriModel":
        """Load a model written by :meth:`save` (a run directory or the model folder in it)."""
        d = Path(directory)
        if not (d / MANIFEST).is_file() and (d / "eri" / MANIFEST).is_file():
            d = d / "eri"
        m = read_manifest(d, MANIFEST, FORMAT, FORMAT_VERSION, "ERI model")
        where = d / MANIFEST
        if m.get("fap_names") != list(FAP_NAMES):
            raise FacesynthError(f"{where}: FAP table differs from this facesynth's; retrain")
        t = read_tensors(d, TENSORS, m, "ERI model")

        def build() -> "EriModel":
            ref = ReferenceFrame(t["reference_points"], check_size(manifest_field(m, "reference_size", where)), t["triangles"])
            check_reference(ref, len(ref.points) if np.ndim(ref.points) == 2 else -1)
            pca = PCAModel(t["pca_mean"], t["pca_components"].astype(np.float32), t["pca_eigenvalues"],
                           float(manifest_field(m, "pca_total_variance", where)))
            check_pca(pca, "ERI PCA")
            regs = {}
            for name, conf in dict(manifest_field(m, "regressors", where)).items():
                pre = f"reg.{name}."
                regs[name] = SVRBank.from_state(conf, _expand_bank_state({k[len(pre):]: v for k, v in t.items() if k.startswith(pre)}))
            return cls(EriConfig.from_dict(manifest_field(m, "config", where)), int(manifest_field(m, "neutral_index", where)),
                       t["neutral_landmarks"], t["forehead"], ref, t["span"], t["neutral_texture"], pca, regs,
                       manifest_field(m, "driver", where), m.get("data_fingerprint", ""), m.get("meta", {}))

        return rebuild(d / TENSORS, "ERI model", build)


def _compact_bank_state(bank: SVRBank) -> dict[str, np.ndarray]:
    """What reloading an SVR bank needs, without repeats: the K machines' support vectors are
    rows of the same training FAPs, so the distinct rows are stored once (``sv_unique``) with
    an index per support vector; the dense (n_sv, K) ``weights`` are rebuilt from ``dual`` and
    ``owner`` on load (docs/eri.md: storing every buffer took tens of MB per variant)."""
    state = {k: v.numpy() for k, v in bank.state_dict().items() if k not in ("weights", "sv")}
    uniq, index = np.unique(bank.sv.numpy(), axis=0, return_inverse=True)
    state.update(sv_unique=uniq, sv_index=index.reshape(-1).astype(np.int32), owner=state["owner"].astype(np.int32))
    return state


def _expand_bank_state(state: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Inverse of :func:`_compact_bank_state` (files with a plain ``sv`` load unchanged)."""
    state = dict(state)
    if "sv_unique" in state:
        state["sv"] = state.pop("sv_unique")[state.pop("sv_index")]
    state["owner"] = state["owner"].astype(np.int64)
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in state.items()}
