"""The statistical face model: Procrustes-aligned shape PCA and appearance PCA on
textures warped (piecewise affine) into the mean shape. Its config holds every part's settings
and its fit runs every part (shape, reference frame, textures, appearance, the restoration
filter and the detail bank) in order, hence its length.

References
----------
T. F. Cootes, G. J. Edwards, C. J. Taylor, "Active appearance models", IEEE TPAMI
23(6), 2001.
"""

from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from facesynth.data.sequence import FaceSequence, validate_landmarks
from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, invert_affine, similarity_fit
from facesynth.landmarks import DEFAULT_SCHEME, folded_triangles, get_scheme, triangle_areas
from facesynth.model.denoise import denoise_model
from facesynth.model.detail import check_detail, fit_detail_bank
from facesynth.model.pca import PCAModel
from facesynth.model.procrustes import generalised_procrustes
from facesynth.model.reference import ReferenceFrame, open_mouth, reference_width, spread_triangles, subset_triangulation
from facesynth.model.restore import apply_path, fit_restoration
from facesynth.model.warp import ToReference, ToTarget, apply_affine_t, candidate_spans, invert_affine_t, similarity_to
from facesynth.progress import bar as progress_bar

log = logging.getLogger(__name__)


@dataclass
class FaceModelConfig:
    """Face model settings (the Hydra ``model/`` group fills this).

    n_shape / n_appearance take precedence over the variance fractions when set.
    """

    n_shape: int | None = None
    shape_variance: float = 0.98
    n_appearance: int | None = None
    appearance_variance: float = 0.98
    reference_width: int | str = 128  # px, or "auto": the training faces' width in the video (reference.py)
    width_guard: float | None = None  # dB a width > 128 px may cost on validation (runs/width_guard.py); None = off
    margin: float = 0.1
    grey: bool = False
    antialias: bool = True  # Gaussian prefilter sigma = scale / 2 when the face is larger than the reference
    clamp_k: float = 3.0
    span_safety: float = 1.3
    span_margin: int = 6  # px added to every triangle's span after the factor (warp.candidate_spans)
    batch_size: int = 32
    # fraction of the aligned training shapes' variance the landmark denoiser keeps: every
    # landmark set the model synthesises from (the regressor's input and the warp target) is
    # projected on that PCA first (FaceModel.denoise); 1 = off; None = the scheme's default
    denoise_variance: float | None = None
    # the reference frame's mouth opening, as a quantile of the training shapes' (the mean
    # shape opened along the data: reference.open_mouth), for every scheme; 0 = the mean's own
    reference_mouth_quantile: float = 0.9
    # a scheme's own fixed mesh (warp_points=mesh): each reference triangle holds at least this
    # quantile of its share of the face's area over the training shapes, over
    # reference.AREA_STRETCH (the mean moved as little as that takes: reference.spread_triangles);
    # 0 = the mean's own
    reference_area_quantile: float = 0.9
    # points the denoiser leaves as given: "eyes" (the eye contours and irises: a driver's
    # blinks and wide eyes outside the avatar's training range stay, as retarget.ShapeSpace
    # keeps them; it doubles the sigma 2 loss, docs/sadm.md) or "none"; None = the scheme's default
    denoise_free: str | None = None
    # the warp's vertices on a scheme with a fixed triangulation: "mesh" (its own, e.g. 884
    # triangles for 478 points) or "sparse" (Delaunay on LandmarkScheme.sparse_points: the
    # iBUG-68 view plus the eye and lip contours, ~197 triangles; the other points are
    # regressor inputs only; faster to render, docs/runtime.md); no effect on ibug68
    warp_points: str = "mesh"
    restore: bool = False  # fit a restoration filter on the training frames (model/restore.py)
    # the filter's strength on the texture's variation from the mean (0..1), its part on the mean
    # texture staying whole: 0 = the mean's part alone, a constant added to the texture before the
    # warp (no filter at run time); sadm.restore_guard moves along this path up to it
    restore_variation: float = 1.0
    # example-based detail (model/detail.py): the strength (0 = off, no bank; 1 = full) of the
    # high band of the k training frames nearest in shape, added on ``detail_parts``
    detail: float = 0.0
    detail_k: int = 4
    detail_parts: str = "mouth"  # "mouth" (interior and lips), "mouth+eyes" or "face"
    detail_band: str = "high"  # "high" (texture - blur), "residual" (- its PCA reconstruction), "texture" (blend to it)
    detail_sigma: float = 2.0  # the high band's Gaussian, px at a 128 px reference (scaled with its width)
    detail_blend: str = "mean"  # the k neighbours per pixel: "mean" (weighted) or "median" (weighted, Weiszfeld)
    detail_feather: float = 0.0  # the parts' mask blurred by this sigma (px at a 128 px reference); 0 = hard edge
    detail_reach: float = 0.0  # fade the detail out beyond this many bank spacings from every training shape; 0 = off


# The settings whose default depends on the landmark scheme (config None): a dense mesh (a
# scheme with a fixed triangulation: hundreds of points, each with its own jitter, on small
# triangles) against a sparse scheme (68 points, Delaunay on the mean; its reenactment drives
# eyelids past the avatar's own range, retarget.ShapeSpace, where a projection on the training
# shapes would pull them back).
# Figures: docs/sadm.md.
SCHEME_DEFAULTS = {
    "dense": {"denoise_variance": 0.999, "denoise_free": "none"},
    "sparse": {"denoise_variance": 1.0, "denoise_free": "none"},
}
DENOISE_FREE = {"eyes": ("eyes", "irises"), "none": ()}  # config value -> the scheme regions left free
WARP_POINTS = ("mesh", "sparse")


def scheme_default(scheme_name: str, name: str):
    """The value of config field ``name`` that None stands for with scheme ``scheme_name``."""
    return SCHEME_DEFAULTS["dense" if get_scheme(scheme_name).triangles is not None else "sparse"][name]


def resolved(cfg: "FaceModelConfig", scheme_name: str, name: str):
    """Config field ``name``, or its scheme default when None."""
    v = getattr(cfg, name)
    return scheme_default(scheme_name, name) if v is None else v


@dataclass
class FaceModel:
    """A fitted face model. Build it with :meth:`fit` (or :func:`load_face_model`).

    Attributes
    ----------
    config : FaceModelConfig
    shape_pca : PCAModel
        Over flattened (P * 2,) Procrustes-aligned shapes (unit-norm scale), P the
        scheme's point count.
    reference : ReferenceFrame
        Mean shape (its mouth opened to ``reference_mouth_quantile``, unless 0; the slivers of
        the scheme's own mesh spread to ``reference_area_quantile``, unless 0) at
        ``reference_width`` pixels, triangulated (the scheme's fixed triangulation, the
        triangles folded on it turned and placed last, or Delaunay).
    appearance_pca : PCAModel
        Over flattened (C * M,) textures in [0, 1], channel-major, M = mask pixels.
    span : np.ndarray
        int64 (T, 2) candidate block sizes for rendering (see :class:`ToTarget`).
    fingerprint : str
        Fingerprint of the training data.
    scheme : str
        Landmark scheme of the training data (``ibug68``, ``mediapipe478``): every
        landmark array given to the model must be in it.
    denoise_pca : PCAModel or None
        Over flattened (P * 2,) Procrustes-aligned training shapes (as ``shape_pca``),
        keeping ``denoise_variance`` of their variance: :meth:`denoise` projects on it.
        None: landmarks are used as given.
    """

    config: FaceModelConfig
    shape_pca: PCAModel
    reference: ReferenceFrame
    appearance_pca: PCAModel
    span: np.ndarray
    fingerprint: str = ""
    meta: dict = field(default_factory=dict)
    scheme: str = DEFAULT_SCHEME.name
    denoise_pca: PCAModel | None = None
    restore_kernel: np.ndarray | None = None  # float32 (k, k): every render's restoration filter (model/restore.py)
    restore_offset: np.ndarray | None = None  # float32 (C * M,): the mean's restoration added to every texture (model/restore.py)
    detail_bank: dict | None = None  # name -> array (model/detail.py BANK_TENSORS); None: no example-based detail

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, seq: FaceSequence, config: FaceModelConfig | None = None, rows=None, progress: bool = True) -> "FaceModel":
        """Fit shape and appearance models on ``seq`` (rows: training rows, default all)."""
        return cls.fit_with_textures(seq, config, rows, progress)[0]

    @classmethod
    def fit_with_textures(
        cls, seq: FaceSequence, config: FaceModelConfig | None = None, rows=None, progress: bool = True
    ) -> tuple["FaceModel", np.ndarray]:
        """:meth:`fit`, also returning the training textures (len(rows), C * M) it sampled."""
        cfg = config or FaceModelConfig()
        scheme = get_scheme(seq.scheme)
        rows = np.arange(len(seq)) if rows is None else np.asarray(rows)
        if len(rows) < 3:
            raise FacesynthError(f"{seq.name}: need at least 3 frames to fit a face model, got {len(rows)}")
        t0 = time.perf_counter()
        lm = seq.landmarks[rows].astype(np.float64)
        cfg = replace(cfg, reference_width=reference_width(cfg.reference_width, lm))  # "auto" resolved: the model records px
        denoise_variance = float(resolved(cfg, scheme.name, "denoise_variance"))
        mouth_q = float(cfg.reference_mouth_quantile)
        free = resolved(cfg, scheme.name, "denoise_free")
        if free not in DENOISE_FREE:
            raise FacesynthError(f"model.denoise_free must be one of {sorted(DENOISE_FREE)}, got {free!r}")
        if not 0 < denoise_variance <= 1:
            raise FacesynthError(f"model.denoise_variance must be a fraction in (0, 1] (1 = off), got {cfg.denoise_variance}")
        if not 0 <= mouth_q <= 1:
            raise FacesynthError(f"model.reference_mouth_quantile must lie in [0, 1] (0 = off), got {cfg.reference_mouth_quantile}")
        if not 0 <= cfg.reference_area_quantile <= 1:
            raise FacesynthError(f"model.reference_area_quantile must lie in [0, 1] (0 = off), got {cfg.reference_area_quantile}")
        check_detail(cfg)
        if not 0 <= cfg.restore_variation <= 1:
            raise FacesynthError(f"model.restore_variation must lie in [0, 1] (0 = the mean's part only), got {cfg.restore_variation}")
        if cfg.warp_points not in WARP_POINTS:
            raise FacesynthError(f"model.warp_points must be one of {WARP_POINTS}, got {cfg.warp_points!r}")
        aligned, mean = generalised_procrustes(lm)
        shape_pca = PCAModel.fit(aligned.reshape(len(rows), -1), cfg.n_shape, cfg.shape_variance)
        free_regions = [scheme.region(r) for r in DENOISE_FREE[free] if r in scheme.regions]
        free_points = np.unique(np.concatenate([np.zeros(0, np.int64), *free_regions]))
        denoise_pca = None if denoise_variance == 1 else denoise_model(aligned, denoise_variance, free_points)
        fixed = None if scheme.triangles is None else scheme.triangulation()
        if fixed is not None and cfg.warp_points == "sparse":
            fixed = subset_triangulation(mean, scheme.sparse_points())
        ref_shape, mouth = mean, {}
        if mouth_q > 0:
            ref_shape, mouth = open_mouth(mean, aligned, scheme.region("inner_lips"), mouth_q, fixed)
        spread = {}
        if fixed is not None and cfg.warp_points == "mesh" and cfg.reference_area_quantile > 0:  # sparse: Delaunay of the mean
            ref_shape, spread = spread_triangles(ref_shape, aligned, fixed, float(cfg.reference_area_quantile))
        ref = ReferenceFrame.from_mean_shape(ref_shape, cfg.reference_width, cfg.margin, fixed)
        model = cls(cfg, shape_pca, ref, None, np.zeros((ref.n_triangles, 2), np.int64), seq.fingerprint,  # type: ignore
                    scheme=scheme.name, denoise_pca=denoise_pca)
        folded = [] if fixed is None else np.flatnonzero(folded_triangles(ref.points, fixed)).tolist()
        if folded:
            log.info("%s: %d triangles of the %s triangulation are folded on the reference shape (%s): kept, "
                     "turned and placed last", seq.name, len(folded), scheme.name, folded)
        canvas_shapes = model.to_canvas(seq.landmarks[rows])[0]
        extremes = model._shape_extremes()
        model.span = candidate_spans(ref, np.concatenate([canvas_shapes, extremes]), cfg.span_safety, cfg.span_margin)
        t1 = time.perf_counter()
        textures = model.sample_textures(seq, rows, progress=progress)
        t2 = time.perf_counter()
        model.appearance_pca = PCAModel.fit(textures, cfg.n_appearance, cfg.appearance_variance)
        t3 = time.perf_counter()
        kernel, restore = fit_restoration(model, seq, rows, textures) if cfg.restore else (None, {})
        if kernel is not None:  # the kernel as fitted is kept for the guard (sadm.restore_guard)
            restore["kernel"] = kernel.tolist()
            apply_path(model, kernel, 1.0 + cfg.restore_variation)
        t4 = time.perf_counter()
        model.detail_bank, detail = fit_detail_bank(model, seq.landmarks[rows], textures) if cfg.detail > 0 else (None, {})
        model.meta = {
            "train_frames": int(len(rows)),
            "fit_seconds": {"shape": t1 - t0, "textures": t2 - t1, "appearance_pca": t3 - t2},
            "sequence": seq.name,
            "triangles_folded_on_mean": folded,
            "reference_mouth": mouth, "reference_spread": spread, **({"restore": {**restore, "seconds": t4 - t3}} if restore else {}),
            **({"detail": {**detail, "seconds": time.perf_counter() - t4}} if detail else {}),
        }
        log.info("face model: %d shape / %d appearance components (%.1f%% / %.1f%% variance), %d mask pixels",
                 shape_pca.n_components, model.appearance_pca.n_components, 100 * shape_pca.explained_variance_ratio,
                 100 * model.appearance_pca.explained_variance_ratio, model.n_pixels)
        return model, textures

    # --------------------------------------------------------------- geometry
    @property
    def n_channels(self) -> int:
        return 1 if self.config.grey else 3

    @property
    def n_pixels(self) -> int:
        return self.sampler().n_pixels

    @property
    def mean_shape(self) -> np.ndarray:
        """(P, 2) Procrustes mean (unit norm)."""
        return self.shape_pca.mean.reshape(-1, 2)

    def align(self, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Similarity-align (N, P, 2) landmarks to the mean shape.

        Returns aligned shapes (N, P, 2) and the (N, 2, 3) transforms used.
        """
        lm = validate_landmarks(landmarks, "landmarks", scheme=self.scheme).astype(np.float64)
        m = similarity_fit(lm, self.mean_shape[None].astype(np.float64))
        return apply_affine(lm, m), m

    def shape_params(self, landmarks: np.ndarray, clamp: bool = False) -> np.ndarray:
        """b_s of (N, P, 2) landmarks -> (N, K_s) float32."""
        aligned, _ = self.align(landmarks)
        b = self.shape_pca.project(aligned.reshape(len(aligned), -1))
        return self.shape_pca.clamp(b, self.config.clamp_k) if clamp else b

    def shape_from_params(self, b_s: np.ndarray) -> np.ndarray:
        """(N, K_s) -> (N, P, 2) shapes in the model's normalised frame."""
        return self.shape_pca.reconstruct(b_s).reshape(len(b_s), -1, 2)

    def to_canvas(self, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map (N, P, 2) frame landmarks into reference-frame pixels by a similarity.

        Returns canvas landmarks (N, P, 2) float32 and the (N, 2, 3) frame->canvas transforms.
        """
        lm = validate_landmarks(landmarks, "landmarks", scheme=self.scheme).astype(np.float64)
        m = similarity_fit(lm, self.reference.points[None].astype(np.float64))
        return apply_affine(lm, m).astype(np.float32), m

    def stretch(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) frame landmarks -> (N,): the largest area ratio of a reference triangle
        (one the reference does not fold) on each frame, mapped to the reference's scale by
        :meth:`to_canvas`: how many times the render stretches the reference's most stretched
        pixels (1 = a similarity of the reference shape; streaks show past ~5: docs/studies/open-mouth.md)."""
        tri = self.reference.triangles
        own = triangle_areas(self.reference.points, tri)
        live = own > 0
        return (triangle_areas(self.to_canvas(landmarks)[0], tri)[:, live] / own[live]).max(1)

    def denoise(self, landmarks: np.ndarray) -> np.ndarray:
        """(N, P, 2) frame landmarks -> float32 (N, P, 2): similarity-aligned to the mean
        shape, projected on ``denoise_pca`` and mapped back (unchanged without it). The
        numpy form of :class:`facesynth.model.denoise.ShapeDenoiser`."""
        lm = validate_landmarks(landmarks, "landmarks", scheme=self.scheme)
        if self.denoise_pca is None:
            return np.asarray(lm, np.float32)
        aligned, m = self.align(lm)
        flat = aligned.reshape(len(aligned), -1)
        proj = self.denoise_pca.reconstruct(self.denoise_pca.project(flat)).astype(np.float64).reshape(aligned.shape)
        return apply_affine(proj, invert_affine(m)).astype(np.float32)

    def _shape_extremes(self) -> np.ndarray:
        """Shapes at +-clamp_k sigma along each shape component, in canvas pixels."""
        k = self.config.clamp_k
        lim = k * np.sqrt(self.shape_pca.eigenvalues)
        b = np.concatenate([np.diag(lim), -np.diag(lim)]).astype(np.float32)
        return self.to_canvas(self.shape_from_params(b))[0]

    # --------------------------------------------------------------- textures
    def sampler(self) -> ToReference:
        """The image -> reference warp module (built once, cached)."""
        if "_sampler" not in self.__dict__:
            self.__dict__["_sampler"] = ToReference(self.reference)
        return self.__dict__["_sampler"]

    def target_warp(self) -> ToTarget:
        """The reference -> target warp module (built once per span, cached)."""
        key = (self.span.tobytes() + (b"" if self.restore_kernel is None else self.restore_kernel.tobytes())
               + (b"" if self.restore_offset is None else hashlib.sha1(self.restore_offset.tobytes()).digest()))
        if self.__dict__.get("_target_warp_key") != key:
            self.__dict__["_target_warp"] = ToTarget(self.reference, self.span, restore=self.restore_kernel,
                                                     offset=self.restore_offset)
            self.__dict__["_target_warp_key"] = key
        return self.__dict__["_target_warp"]

    def sample_textures(self, seq: FaceSequence, rows=None, progress: bool = False) -> np.ndarray:
        """Textures of sequence rows in the reference frame: (N, C * M) float32 in [0, 1]."""
        rows = np.arange(len(seq)) if rows is None else np.asarray(rows)
        sampler = self.sampler()
        bs = self.config.batch_size
        out = np.empty((len(rows), self.n_channels * sampler.n_pixels), np.float32)
        frames = seq.iter_frames(rows)
        bar = progress_bar(total=len(rows), desc="textures", unit="frame", enabled=progress)
        for start in range(0, len(rows), bs):
            chunk = rows[start : start + bs]
            imgs = np.stack([next(frames) for _ in chunk])
            out[start : start + len(chunk)] = self.textures_from_images(imgs, seq.landmarks[chunk], sampler)
            bar.update(len(chunk))
        bar.close()
        return out

    def textures_from_images(self, images: np.ndarray, landmarks: np.ndarray, sampler: ToReference | None = None) -> np.ndarray:
        """uint8 (B, H, W, 3) images + (B, P, 2) landmarks -> (B, C * M) float32 textures.

        With ``config.antialias`` each image is low-pass filtered before sampling, with a
        Gaussian of sigma = s / 2 where s (> 1) is frame pixels per reference pixel: point
        sampling a face larger than the reference would alias hair, lashes and pores into
        noise that moves with sub-pixel landmark jitter.
        """
        sampler = sampler or self.sampler()
        if self.config.antialias:
            images = self._prefilter(images, landmarks)
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)
        if self.config.grey:
            x = (x * torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)
        with torch.no_grad():
            tex = sampler(x, torch.from_numpy(np.asarray(landmarks, np.float32)))
        return tex.reshape(len(images), -1).numpy()

    def frame_scale(self, landmarks: np.ndarray) -> np.ndarray:
        """Frame pixels per reference pixel for (B, P, 2) landmarks -> (B,)."""
        _, m = self.to_canvas(landmarks)
        return 1.0 / np.sqrt(np.abs(np.linalg.det(m[:, :, :2])))

    def _prefilter(self, images: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        import cv2

        out = np.empty_like(images)
        for i, (img, s) in enumerate(zip(images, self.frame_scale(landmarks), strict=True)):
            out[i] = cv2.GaussianBlur(img, (0, 0), s / 2) if s > 1 else img
        return out

    def appearance_params(self, textures: np.ndarray, clamp: bool = False) -> np.ndarray:
        """(N, C * M) textures -> (N, K_g) b_g."""
        b = self.appearance_pca.project(textures)
        return self.appearance_pca.clamp(b, self.config.clamp_k) if clamp else b

    def texture_from_params(self, b_g: np.ndarray) -> np.ndarray:
        """(N, K_g) -> (N, C * M) textures (not clipped)."""
        return self.appearance_pca.reconstruct(b_g)

    def texture_images(self, textures: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(N, C * M) textures -> float32 (N, H, W, C) reference images."""
        t = torch.from_numpy(np.asarray(textures, np.float32)).reshape(len(textures), self.n_channels, -1)
        return self.sampler().to_image(t, fill).permute(0, 2, 3, 1).numpy()

    def render(self, textures: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Warp textures onto frame landmarks (after :meth:`denoise`), in the reference-scale crop.

        Parameters
        ----------
        textures : (B, C * M) float32
        landmarks : (B, P, 2) frame pixels

        Returns
        -------
        crop : float32 (B, H, W, C) in [0, 1]
        mask : float32 (B, H, W)
        placement : float64 (B, 2, 3) affine map from crop pixels to frame pixels
        """
        canvas, m = self.to_canvas(self.denoise(landmarks))
        with torch.no_grad():
            img, mask = self.target_warp()(
                torch.from_numpy(np.asarray(textures, np.float32)).reshape(len(textures), self.n_channels, -1).clamp(0, 1),
                torch.from_numpy(canvas),
            )
        placement = invert_affine_t(torch.from_numpy(m)).numpy()
        return img.permute(0, 2, 3, 1).numpy(), mask[:, 0].numpy(), placement

    def describe(self) -> dict:
        """Sizes and variance figures (for reports)."""
        return {
            "n_shape": self.shape_pca.n_components,
            "n_appearance": self.appearance_pca.n_components,
            "shape_variance_kept": self.shape_pca.explained_variance_ratio,
            "appearance_variance_kept": self.appearance_pca.explained_variance_ratio,
            "reference_size": list(self.reference.size),
            "n_triangles": self.reference.n_triangles,
            "n_denoise_components": 0 if self.denoise_pca is None else self.denoise_pca.n_components,
            "n_mask_pixels": self.n_pixels,
            "channels": self.n_channels,
            "config": asdict(self.config),
        }


__all__ = ["FaceModel", "FaceModelConfig", "apply_affine_t", "similarity_to"]
