"""Synthesis from landmarks alone, as one torch graph (the graph that ONNX export traces):

    landmarks (frame px) -> similarity alignment -> b_s (clamped) -> shape features
      -> SADM regressor (+ gaze path, when the scheme has irises) -> b_g (clamped)
      -> texture in the reference frame
      -> piecewise-affine warp to the landmarks -> crop + mask + placement in the frame

When the face model has a denoise PCA (:meth:`FaceModel.denoise`), the model's points are
projected on it first, and everything after reads the denoised landmarks.

The landmarks may have more points than the face model (``ibug68+iris``: 78 points, a
68-point face model): the model's path takes the first ones, the gaze path
(:mod:`facesynth.sadm.gaze`) reads the irises.

Pasting the crop into a frame (feathered) is :func:`composite`, outside the graph.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.model.denoise import shape_denoiser
from facesynth.model.detail import DetailTransfer
from facesynth.model.face_model import FaceModel
from facesynth.model.warp import ToTarget, apply_affine_t, invert_affine_t, similarity_to
from facesynth.regressors.base import Regressor

FEATURE_KINDS = ("bs", "landmarks", "bs+landmarks", "landmarks_rigid")
# points that expressions barely move, the scheme's ``rigid_nose_eyes`` region (iBUG-68: nose
# bridge and base 27-35, eye corners 36, 39, 42, 45): ``landmarks_rigid`` aligns on these alone
RIGID_REGION = "rigid_nose_eyes"
RIGID_POINTS = get_scheme("ibug68").regions[RIGID_REGION]  # the ibug68 ones


class ShapeEncoder(nn.Module):
    """Frame landmarks -> aligned shape and shape parameters.

    Forward
    -------
    landmarks : (B, P, 2) float32 frame pixels
    returns : aligned (B, P, 2) in the model's normalised frame, b_s (B, K_s) clamped
      to +-k sqrt(lambda) when ``clamp_k > 0``.
    """

    def __init__(self, model: FaceModel, clamp: bool = True):
        super().__init__()
        pca = model.shape_pca
        self.register_buffer("mean_shape", torch.from_numpy(pca.mean.reshape(-1, 2).copy()))
        self.register_buffer("mean", torch.from_numpy(pca.mean.copy()))
        self.register_buffer("components", torch.from_numpy(pca.components.copy()))
        lim = model.config.clamp_k * np.sqrt(pca.eigenvalues) if clamp else np.full(pca.n_components, np.inf)
        self.register_buffer("limit", torch.from_numpy(lim.astype(np.float32)))

    def forward(self, landmarks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        aligned = apply_affine_t(landmarks, similarity_to(landmarks, self.mean_shape))
        b = torch.matmul(aligned.reshape(aligned.shape[0], -1) - self.mean, self.components.t())
        return aligned, torch.clamp(b, -self.limit, self.limit)


class ShapeFeatures(nn.Module):
    """Regressor inputs from the aligned shape: ``bs`` (b_s, the paper), ``landmarks``
    (the aligned coordinates minus the mean, scaled to pixels of a 100-px face), or both;
    ``landmarks_rigid``: as ``landmarks`` but the similarity alignment is re-fitted on
    the scheme's :data:`RIGID_REGION` alone (the eye corners and the nose), so that an expression
    (an open mouth, raised brows) does not shift, rotate or rescale the whole shape the
    way a 68-point Procrustes fit does. A similarity of a similarity-aligned shape is a
    similarity of the frame landmarks, so this equals aligning the frame landmarks on the
    rigid points directly (least squares, Umeyama 1991).

    Forward: aligned (B, P, 2), b_s (B, K_s) -> features (B, F).
    """

    def __init__(self, model: FaceModel, kind: str = "bs"):
        super().__init__()
        if kind not in FEATURE_KINDS:
            raise FacesynthError(f"sadm.features must be one of {FEATURE_KINDS}, got {kind!r}")
        self.kind = kind
        self.register_buffer("mean", torch.from_numpy(model.shape_pca.mean.copy()))
        mean = model.shape_pca.mean.reshape(-1, 2)
        self.scale = float(100.0 / (mean[:, 0].max() - mean[:, 0].min()))
        if kind == "landmarks_rigid":
            self.rigid = get_scheme(model.scheme).region(RIGID_REGION).tolist()
            self.register_buffer("rigid_mean", torch.from_numpy(mean[self.rigid].astype(np.float32).copy()))

    def forward(self, aligned: torch.Tensor, b_s: torch.Tensor) -> torch.Tensor:
        if self.kind == "bs":
            return b_s
        if self.kind == "landmarks_rigid":
            aligned = apply_affine_t(aligned, similarity_to(aligned[:, self.rigid], self.rigid_mean))
            return (aligned.reshape(aligned.shape[0], -1) - self.mean) * self.scale
        lm = (aligned.reshape(aligned.shape[0], -1) - self.mean) * self.scale
        return lm if self.kind == "landmarks" else torch.cat([b_s, lm], 1)

    @staticmethod
    def numpy(model: FaceModel, landmarks: np.ndarray, kind: str = "bs", clamp: bool = True) -> np.ndarray:
        """The same features computed from (N, P, 2) frame landmarks -> (N, F) float32
        (``clamp``: b_s clamped as by the graph's :class:`ShapeEncoder`)."""
        enc = ShapeEncoder(model, clamp)
        feat = ShapeFeatures(model, kind)
        with torch.no_grad():
            aligned, b = enc(torch.from_numpy(np.asarray(landmarks, np.float32)))
            return feat(aligned, b).numpy()


class GlobalAppearance(nn.Module):
    """Shape features -> b_g (regressor) -> clamp -> texture (B, C, M) via the appearance PCA.

    ``basis``: None (``b_g @ components`` in float32), or the export's int8 basis
    (:class:`facesynth.sadm.quantize.Int8Basis`, set by ``quantize_synthesizer``) mapping
    b_g (B, K) to the deviation from the mean texture (B, C M).
    ``gaze``: None, or a :class:`facesynth.sadm.gaze.GazePath` whose output (from the input
    landmarks, (B, P, 2) frame pixels) is added to the regressor's b_g before the clamp;
    ``gaze_inputs``: None, or a :class:`facesynth.sadm.gaze.GazeInputs` whose output is
    appended to the regressor's inputs.
    """

    def __init__(self, model: FaceModel, regressor: Regressor, features: str = "bs", clamp: bool = True,
                 gaze: nn.Module | None = None, gaze_inputs: nn.Module | None = None):
        super().__init__()
        self.gaze = gaze
        self.gaze_inputs = gaze_inputs
        pca = model.appearance_pca
        self.features = ShapeFeatures(model, features)
        self.regressor = regressor
        self.channels = model.n_channels
        self.register_buffer("mean", torch.from_numpy(pca.mean.copy()))
        self.register_buffer("components", torch.from_numpy(pca.components.copy()))
        lim = model.config.clamp_k * np.sqrt(pca.eigenvalues) if clamp else np.full(pca.n_components, np.inf)
        self.register_buffer("limit", torch.from_numpy(lim.astype(np.float32)))
        self.basis: nn.Module | None = None

    def shallow_copy(self) -> "GlobalAppearance":
        """A copy sharing every tensor and submodule, whose buffers and submodules can be
        replaced without touching this one (export-time variants: compression, int8)."""
        out = copy.copy(self)
        out._buffers = dict(self._buffers)
        out._modules = dict(self._modules)
        return out

    def deviation(self, b_g: torch.Tensor) -> torch.Tensor:
        """Texture deviation from the mean (B, C M) of clamped coefficients b_g (B, K)."""
        return torch.matmul(b_g, self.components) if self.basis is None else self.basis(b_g)

    def raw_params(self, aligned: torch.Tensor, b_s: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """b_g (B, K_g) before the clamp: the regressor's (gaze inputs appended to its inputs),
        plus the gaze path's, both from ``landmarks``."""
        if self.needs_landmarks and landmarks is None:
            raise FacesynthError("this appearance model reads the irises (gaze): it needs the input landmarks")
        x = self.features(aligned, b_s)
        if self.gaze_inputs is not None:
            x = torch.cat([x, self.gaze_inputs(landmarks)], 1)
        b_g = self.regressor(x)
        return b_g + self.gaze(landmarks) if self.gaze is not None and self.gaze.target == "params" else b_g

    def texture_correction(self, landmarks: torch.Tensor | None) -> torch.Tensor | float:
        """The gaze path's texture correction (B, C M) when it corrects the texture, else 0."""
        return self.gaze(landmarks) if self.gaze is not None and self.gaze.target != "params" else 0.0

    def add_texture_correction(self, texture: torch.Tensor, landmarks: torch.Tensor | None) -> torch.Tensor:
        """``texture + texture_correction(landmarks)`` (B, C M), computed on the gaze path's
        eye columns only (:meth:`facesynth.sadm.gaze.GazePath.add_to`)."""
        if self.gaze is None or self.gaze.target == "params":
            return texture
        return self.gaze.add_to(texture, landmarks)

    @property
    def needs_landmarks(self) -> bool:
        return self.gaze is not None or self.gaze_inputs is not None

    def params(self, aligned: torch.Tensor, b_s: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        """b_g (B, K_g), clamped (``landmarks``: the input (B, P, 2), for the gaze path)."""
        return torch.clamp(self.raw_params(aligned, b_s, landmarks), -self.limit, self.limit)

    def forward(self, aligned: torch.Tensor, b_s: torch.Tensor, landmarks: torch.Tensor | None = None) -> torch.Tensor:
        tex = self.add_texture_correction(self.mean + self.deviation(self.params(aligned, b_s, landmarks)), landmarks)
        return tex.reshape(tex.shape[0], self.channels, -1)


def detail_transfer(model: FaceModel, strength: float | None = None) -> DetailTransfer | None:
    """The face model's example-based detail (:mod:`facesynth.model.detail`) at ``strength``
    (default: its ``detail`` setting); None without a bank or at strength 0."""
    s = float(model.config.detail if strength is None else strength)
    if model.detail_bank is None or s <= 0:
        return None
    return DetailTransfer(model.detail_bank, model.config.detail_k, s, model.n_pixels)


class Synthesizer(nn.Module):
    """The whole synthesis graph.

    Forward
    -------
    landmarks : (B, P, 2) float32 frame pixels in landmark scheme ``scheme`` (default: the
      face model's; P = ``n_points``; the face model uses the first ``model_points`` of them,
      e.g. the 68 dlib points of ``ibug68+iris``)
    returns : crop (B, C, H, W) float32 in [0, 1] (zeros outside the face), mask (B, 1, H, W)
      in {0, 1}, placement (B, 2, 3) affine map from crop pixels to frame pixels.
    """

    def __init__(self, model: FaceModel, appearance: nn.Module, clamp_shape: bool = True, scheme: str | None = None):
        super().__init__()
        scheme = scheme or model.scheme
        self.scheme = scheme  # the landmark scheme of the input (recorded by the export)
        self.model_points = int(model.shape_pca.mean.shape[0]) // 2
        self.n_points = get_scheme(scheme).n_points
        if get_scheme(scheme).base_scheme().n_points != self.model_points:
            raise FacesynthError(f"landmark scheme {scheme!r} does not fit a face model of {self.model_points} points")
        self.encoder = ShapeEncoder(model, clamp_shape)
        self.appearance = appearance
        self.warp = ToTarget(model.reference, model.span, restore=model.restore_kernel, offset=model.restore_offset)
        self.detail = detail_transfer(model)
        # FaceModel.denoise on the model's points, the rest as given (identity without a denoise PCA)
        self.denoise = shape_denoiser(model.denoise_pca)
        self.register_buffer("ref_points", torch.from_numpy(model.reference.points.copy()))

    def with_appearance(self, appearance: nn.Module) -> "Synthesizer":
        """A copy (eval mode) with another appearance model, sharing everything else."""
        out = copy.copy(self)
        out._modules = dict(self._modules)
        out.appearance = appearance
        return out.eval()

    def model_landmarks(self, landmarks: torch.Tensor) -> torch.Tensor:
        """(B, P, 2) input -> (B, model_points, 2): the points the face model takes."""
        return landmarks if self.n_points == self.model_points else landmarks[:, : self.model_points]

    def texture(self, landmarks: torch.Tensor) -> torch.Tensor:
        """Predicted reference-frame texture (B, C, M), clipped to [0, 1]."""
        return self._texture(self.denoise(landmarks))

    def _texture(self, landmarks: torch.Tensor) -> torch.Tensor:
        aligned, b_s = self.encoder(self.model_landmarks(landmarks))
        if getattr(self.appearance, "needs_landmarks", False):
            tex = torch.clamp(self.appearance(aligned, b_s, landmarks), 0.0, 1.0)
        else:
            tex = torch.clamp(self.appearance(aligned, b_s), 0.0, 1.0)
        return tex if self.detail is None else self.detail(tex, aligned)

    def forward(self, landmarks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        landmarks = self.denoise(landmarks)
        tex = self._texture(landmarks)
        landmarks = self.model_landmarks(landmarks)
        to_canvas = similarity_to(landmarks, self.ref_points)
        crop, mask = self.warp(tex, apply_affine_t(landmarks, to_canvas))
        return crop, mask, invert_affine_t(to_canvas)
