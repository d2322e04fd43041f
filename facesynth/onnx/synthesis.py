"""ONNX export of the whole synthesis graph (torch side; the runtime side is torch-free).

    landmarks (B, P, 2) frame px -> crop (B, C, H, W) in [0, 1], mask (B, 1, H, W),
                                     placement (B, 2, 3) crop px -> frame px

:class:`SynthesisGraph` computes exactly what :class:`facesynth.sadm.synthesis.Synthesizer`
computes (the parity tests hold it to 1e-4), rewritten for a short ONNX graph: both
similarity alignments (to the model's mean shape and to the reference frame) share one
closed-form Umeyama solve as one matmul, the PCA projections fold their means into
constants, and the piecewise-affine render warp is :class:`facesynth.model.warp.ToTarget`
(scanline coverage counting, flat element gathers). Every regressor is called as its own
``nn.Module``, so whatever the registry holds exports the same way.

The ONNX file records its opset and metadata properties (see :data:`METADATA_KEYS`), which
:class:`facesynth.runtime.Renderer` checks before running.
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from facesynth import __version__
from facesynth.contract import (
    CODE_LEVELS_KEY,
    FLOAT_PARITY_TOL,
    OPSET,
    OUTPUT_NAMES,
    SYNTHESIS_FORMAT,
    SYNTHESIS_INPUT,
    SYNTHESIS_METADATA_KEYS,
    SYNTHESIS_OUTPUT_LAYOUT,
)
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.onnx.avatar import run_avatar_metadata
from facesynth.onnx.common import SimilarityAlignment, check_parity, save_graph
from facesynth.onnx.config import BASIS_KINDS, DEFAULT_BASIS, DEFAULT_COMPONENTS
from facesynth.onnx.int8check import scaled_coefficients, tie_allowance
from facesynth.rundir import load_synthesizer, training_landmarks
from facesynth.runtime.renderer import Renderer
from facesynth.sadm.compress import compress_synthesizer
from facesynth.sadm.quantize import quantize_synthesizer
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

log = logging.getLogger(__name__)

METADATA_KEYS = SYNTHESIS_METADATA_KEYS  # every file carries these (facesynth.contract)


class SynthesisGraph(nn.Module):
    """The export form of a :class:`Synthesizer` (same outputs, fewer ONNX nodes).

    Forward
    -------
    landmarks : (B, P, 2) float32 frame pixels in the synthesizer's scheme (P = 68, 78, 478;
      the face model takes the first ``model_points``; a gaze path, when there is one, reads
      the irises)
    returns : crop (B, C, H, W), mask (B, 1, H, W), placement (B, 2, 3)
    """

    def __init__(self, syn: Synthesizer):
        super().__init__()
        enc = syn.encoder
        self.n_points, self.model_points = syn.n_points, syn.model_points
        self.gaze = getattr(syn.appearance, "needs_landmarks", False)
        self.appearance = syn.appearance
        self.warp = syn.warp
        self.denoise = syn.denoise
        self.detail = getattr(syn, "detail", None)  # the example-based detail (model/detail.py), or None
        # both similarity alignments (to the model's mean shape and to the reference frame) in one solve
        self.align = SimilarityAlignment([enc.mean_shape.double().numpy(), syn.ref_points.double().numpy()])
        # shape parameters: (aligned - mean) @ P^T = aligned @ P^T - mean @ P^T
        self.register_buffer("shape_proj", enc.components.t().contiguous())
        self.register_buffer("shape_offset", -(enc.mean @ enc.components.t()))
        self.register_buffer("shape_limit", enc.limit.clone())
        self.global_appearance = isinstance(syn.appearance, GlobalAppearance)
        if self.global_appearance:
            app = syn.appearance
            self.channels = app.channels
            self.n_tex = int(app.mean.shape[0]) // int(app.channels)  # a Python int: no Shape op when traced
            self.register_buffer("app_limit", app.limit.clone())
            self.register_buffer("app_mean", app.mean.clone())

    def forward(self, landmarks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if not isinstance(self.denoise, nn.Identity):  # FaceModel.denoise on the model's points
            landmarks = self.denoise(landmarks)
        full = landmarks
        if self.n_points != self.model_points:
            landmarks = landmarks[:, : self.model_points]
        both, ab, mu = self.align(landmarks)  # (B, 2, P_model, 2): to the mean shape, to the canvas
        aligned, canvas = both[:, 0], both[:, 1]
        b_s = torch.matmul(aligned.flatten(1), self.shape_proj) + self.shape_offset
        b_s = torch.minimum(torch.maximum(b_s, -self.shape_limit), self.shape_limit)
        if self.global_appearance:
            b_g = self.appearance.raw_params(aligned, b_s, full)  # regressor (+ gaze inputs / gaze path)
            b_g = torch.minimum(torch.maximum(b_g, -self.app_limit), self.app_limit)
            # float32 matmul, or the int8 basis (MatMulInteger; facesynth.sadm.quantize)
            tex = self.appearance.deviation(b_g) + self.app_mean
            if self.gaze:  # the gaze path's texture correction, on its eye columns only
                tex = self.appearance.add_texture_correction(tex, full)
            tex = torch.clamp(tex, 0.0, 1.0)
            tex = tex.reshape(-1, self.channels, self.n_tex)
        else:
            tex = torch.clamp(self.appearance(aligned, b_s, full) if self.gaze else self.appearance(aligned, b_s), 0.0, 1.0)
        if self.detail is not None:  # in the reference frame, before the warp (model/detail.py)
            tex = self.detail(tex, aligned)
        crop, mask = self.warp(tex, canvas)
        return crop, mask, self.align.placement(ab, mu, 1)  # canvas px -> frame px


def regressor_name(syn: Synthesizer) -> str:
    reg = getattr(syn.appearance, "regressor", None)
    return str(getattr(reg, "name", type(syn.appearance).__name__))


def export_synthesizer(syn: Synthesizer, path: str | os.PathLike, metadata: dict | None = None, opset: int = OPSET) -> Path:
    """Export ``syn`` to one ONNX file (written atomically) with a dynamic batch axis.

    Parameters
    ----------
    syn : Synthesizer
    path : output ``.onnx`` file
    metadata : dict, optional
        Extra metadata properties (e.g. ``data_fingerprint``, ``run``); values are stored as
        strings (JSON for non-strings). The standard keys of :data:`METADATA_KEYS` are filled
        from ``syn`` unless given.
    opset : int

    Returns
    -------
    Path of the written file.
    """
    path = Path(path)
    graph = SynthesisGraph(syn.eval()).eval()
    ref = syn.warp.ref_size
    meta = {
        "facesynth_version": __version__,
        "format": SYNTHESIS_FORMAT,
        "regressor": regressor_name(syn),
        "landmark_scheme": syn.scheme,
        "n_landmarks": syn.n_points,
        "reference_size": list(ref),
        "canvas_size": list(syn.warp.canvas),
        "channels": int(getattr(syn.appearance, "channels", 3)),
        "data_fingerprint": "",
        "output_layout": SYNTHESIS_OUTPUT_LAYOUT,
        "opset": opset,
        "n_scanline_events": syn.warp.n_scanline_events,
    }
    if isinstance(syn.appearance, GlobalAppearance):
        meta["appearance_basis"] = "float32" if syn.appearance.basis is None else "int8"
        if syn.appearance.basis is not None:  # the runtime recognises saturating codes by it (facesynth.runtime.cpu)
            meta[CODE_LEVELS_KEY] = syn.appearance.basis.levels
    meta.update(metadata or {})
    example = torch.from_numpy(_example_landmarks(syn))
    save_graph(graph, example, path, SYNTHESIS_INPUT, OUTPUT_NAMES, meta, opset,
               "facesynth synthesis graph: landmarks -> face crop, mask, placement")
    return path


def _example_landmarks(syn: Synthesizer) -> np.ndarray:
    """(2, P, 2) plausible frame landmarks (the reference shape, shifted) for tracing; points
    beyond the face model's (the irises of ``ibug68+iris``) at the middle of each eye's
    corners, else at the shape's centroid."""
    pts = syn.ref_points.detach().cpu().numpy().astype(np.float32)
    extra = syn.n_points - len(pts)
    if extra > 0:
        pts = np.concatenate([pts, np.repeat(pts.mean(0, keepdims=True), extra, 0)])
        sch = get_scheme(syn.scheme)
        if "iris_centres" in sch.regions:
            c, i = sch.region("eye_corners"), sch.region("iris_centres")
            pts[i] = 0.5 * (pts[c[[0, 2]]] + pts[c[[1, 3]]]) + np.float32([[1.5, -0.5], [-1.0, 0.5]])
    return np.stack([pts + 20.0, pts * 1.1 + 5.0]).astype(np.float32)


def compress_for_export(
    syn: Synthesizer, landmarks, components: int | None = DEFAULT_COMPONENTS, predicted_variance: float | None = None,
) -> tuple[Synthesizer, dict]:
    """Apply :func:`facesynth.sadm.compress.compress_synthesizer` for export and return the
    metadata that records it. ``components`` 0/None and no ``predicted_variance``, or a
    model with at most ``components`` components: unchanged (``compression: none``).
    ``landmarks`` is an array or a callable returning one (only called when needed)."""
    app = syn.appearance
    if not isinstance(app, GlobalAppearance):
        return syn, {"compression": "none"}
    k_all = int(app.components.shape[0])
    if predicted_variance is None and (not components or int(components) >= k_all):
        return syn, {"compression": "none", "appearance_components": k_all, "appearance_components_full": k_all}
    lm = landmarks() if callable(landmarks) else landmarks
    out, info = compress_synthesizer(syn, np.asarray(lm, np.float32), None if predicted_variance is not None else int(components),
                                     predicted_variance)
    info = {k: v for k, v in info.items() if k != "kept_components"}
    info["compression"] = "predicted_variance_topk"
    if predicted_variance is not None:
        info["compression_predicted_variance_target"] = float(predicted_variance)
    return out, info


def quantize_for_export(syn: Synthesizer, landmarks, basis: str = DEFAULT_BASIS) -> tuple[Synthesizer, dict]:
    """Apply :func:`facesynth.sadm.quantize.quantize_synthesizer` when ``basis`` is "int8"
    and return the metadata that records it (``appearance_basis`` and, measured over
    ``landmarks`` (array or callable), ``quantization_psnr_vs_float_db``). "float32": unchanged."""
    if basis not in BASIS_KINDS:
        raise FacesynthError(f"appearance basis must be one of {BASIS_KINDS}, got {basis!r}")
    if not isinstance(syn.appearance, GlobalAppearance):
        return syn, {}
    if basis == "float32":
        return syn, {"appearance_basis": "float32"}
    if not torch.isfinite(syn.appearance.limit).all():
        log.warning("int8 basis needs the appearance clamping limits (this model has clamping off): float32 basis kept")
        return syn, {"appearance_basis": "float32"}
    try:
        lm = landmarks() if callable(landmarks) else landmarks
    except FacesynthError as exc:  # the measurement is optional; quantizing needs no landmarks
        log.info("int8 basis: not measured against the float basis (%s)", exc)
        lm = None
    return quantize_synthesizer(syn, lm)


def export_run(
    run_dir: str | os.PathLike, out: str | os.PathLike, opset: int = OPSET,
    components: int | None = DEFAULT_COMPONENTS, predicted_variance: float | None = None, landmarks=None,
    basis: str = DEFAULT_BASIS,
) -> tuple[Path, Synthesizer, dict]:
    """``facesynth export RUN --out model.onnx``: load a run, compress its appearance
    (:func:`compress_for_export`; ``landmarks`` default: the run's training landmarks),
    quantize its basis (:func:`quantize_for_export`) and export it. Returns the file, the
    exported (compressed, quantized) synthesizer and the metadata."""
    syn, meta = prepare_run(run_dir, components, predicted_variance, landmarks, basis)
    return export_synthesizer(syn, out, meta, opset), syn, meta


def prepare_run(run_dir: str | os.PathLike, components: int | None = DEFAULT_COMPONENTS,
                predicted_variance: float | None = None, landmarks=None,
                basis: str = DEFAULT_BASIS) -> tuple[Synthesizer, dict]:
    """A run's synthesizer as :func:`export_run` exports it (compressed, quantized) and its
    metadata (the avatar's included), without writing a file."""
    syn, meta = load_synthesizer(run_dir)
    lm = functools.cache(lambda: landmarks if landmarks is not None else training_landmarks(run_dir))  # loaded once, if needed
    syn, info = compress_for_export(syn, lm, components, predicted_variance)
    meta.update(info)
    syn, info = quantize_for_export(syn, lm, basis)
    meta.update(info)
    meta.update(run_avatar_metadata(run_dir, syn))
    return syn, meta


def run_torch(module: nn.Module, appearance: nn.Module, feeds: dict) -> tuple[tuple[np.ndarray, ...], np.ndarray | None]:
    """Run ``module`` on ``feeds`` (numpy, in its inputs' order): its outputs as numpy, and with
    an int8 basis in ``appearance`` the (B, K) scaled coefficients that the basis rounded
    (:meth:`facesynth.sadm.quantize.Int8Basis.scaled`; None without one)."""
    basis = getattr(appearance, "basis", None)
    scaled = []
    hook = basis.register_forward_pre_hook(lambda m, args: scaled.append(m.scaled(args[0]))) if basis is not None else None
    try:
        with torch.no_grad():
            out = module(*(torch.from_numpy(np.asarray(v)) for v in feeds.values()))
    finally:
        if hook is not None:
            hook.remove()
    out = tuple(t.numpy() for t in (out if isinstance(out, tuple) else (out,)))
    return out, (torch.cat(scaled).double().numpy() if basis is not None else None)


def torch_reference(module: nn.Module, appearance: nn.Module, path: str | os.PathLike, feeds: dict,
                    tol: float = FLOAT_PARITY_TOL) -> tuple[tuple[np.ndarray, ...], np.ndarray | float]:
    """Run ``module`` (the torch graph of the file ``path``) on ``feeds`` (numpy, in the file's
    input order) and apply the int8 parity contract (:data:`facesynth.contract.FLOAT_PARITY_TOL`).

    Returns the outputs as numpy, and the crop tolerance: ``tol``, or with an int8 basis in
    ``appearance`` a (B,) array, ``tol`` plus what the codes that ONNX Runtime rounds the other
    way on a tie may move each frame's crop by (:func:`facesynth.onnx.int8check.tie_allowance`,
    which raises FacesynthError for any other disagreement of the codes).
    """
    out, x_torch = run_torch(module, appearance, feeds)
    if x_torch is None:
        return out, tol
    basis = appearance.basis
    return out, tol + tie_allowance(basis.codes.numpy(), basis.col_scale.numpy(), scaled_coefficients(path, feeds), x_torch)


def check_export(syn: Synthesizer, path: str | os.PathLike, landmarks: np.ndarray | None = None,
                 tol: float = FLOAT_PARITY_TOL) -> float:
    """Run ``path`` in ONNX Runtime and ``syn`` in torch on the same landmarks.

    Returns the largest absolute crop difference; raises FacesynthError above ``tol``, on
    NaN, or when the masks differ in more than 0.1% of pixels (:func:`check_parity`). With
    an int8 basis, by the int8 parity contract (:func:`torch_reference`): a coefficient on a
    rounding tie may round either way in the two implementations, which adds its one code
    step to that frame's tolerance.
    """
    x = _example_landmarks(syn) if landmarks is None else np.asarray(landmarks, np.float32)
    crop, mask, _ = Renderer(path).render(x)
    (t_crop, t_mask, _), frame_tol = torch_reference(syn, syn.appearance, path, {SYNTHESIS_INPUT: x}, tol)
    return check_parity(path, (crop, mask), (t_crop, t_mask), frame_tol)
