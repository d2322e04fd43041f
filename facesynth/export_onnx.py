"""ONNX export of the whole synthesis graph (torch side; the runtime side is torch-free).

    landmarks (B, 68, 2) frame px -> crop (B, C, H, W) in [0, 1], mask (B, 1, H, W),
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
import json
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from facesynth import __version__
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path
from facesynth.onnx_passes import int32_indices
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

log = logging.getLogger(__name__)

OPSET = 18
INPUT_NAME = "landmarks"
OUTPUT_NAMES = ("crop", "mask", "placement")
OUTPUT_LAYOUT = (
    "crop: float32 (B, C, H, W) in [0, 1], zeros outside the face; mask: float32 (B, 1, H, W) in {0, 1}; "
    "placement: float32 (B, 2, 3) affine map from crop pixels (x, y) to frame pixels"
)
METADATA_KEYS = (
    "facesynth_version", "format", "regressor", "landmark_scheme", "n_landmarks", "reference_size",
    "channels", "data_fingerprint", "output_layout", "opset",
)
FORMAT = "facesynth.synthesis.onnx/1"


class SynthesisGraph(nn.Module):
    """The export form of a :class:`Synthesizer` (same outputs, fewer ONNX nodes).

    Forward
    -------
    landmarks : (B, 68, 2) float32 frame pixels, iBUG order
    returns : crop (B, C, H, W), mask (B, 1, H, W), placement (B, 2, 3)
    """

    def __init__(self, syn: Synthesizer):
        super().__init__()
        enc = syn.encoder
        self.appearance = syn.appearance
        self.warp = syn.warp
        targets = [enc.mean_shape.double(), syn.ref_points.double()]  # (68, 2) each
        cols, mus = [], []
        for d in targets:
            mu = d.mean(0)
            dc = d - mu
            perp = torch.stack([dc[:, 1], -dc[:, 0]], -1)  # s . perp = s_x d_y - s_y d_x
            cols += [dc.reshape(-1), perp.reshape(-1)]
            mus.append(mu)
        # (136, 4): [a, b] of the closed-form 2D similarity to each target (Umeyama)
        self.register_buffer("umeyama", torch.stack(cols, 1).float())
        # [sa, sb] -> row-major M with aligned = s @ M, M = [[sa, sb], [-sb, sa]]
        to_m = torch.tensor([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, -1.0, 0.0]])
        self.register_buffer("to_m", torch.block_diag(to_m, to_m))  # (4, 8)
        self.register_buffer("target_mean", torch.stack(mus).float().reshape(2, 1, 2))
        self.register_buffer("ref_mean", mus[1].float().reshape(1, 2, 1))
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
        mu = landmarks.mean(1, keepdim=True)  # (B, 1, 2)
        s = landmarks - mu
        var = (s * s).flatten(1).sum(1, keepdim=True)  # (B, 1)
        ab = torch.matmul(s.flatten(1), self.umeyama) / var  # (B, 4): sa, sb (model), sa, sb (canvas)
        m = torch.matmul(ab, self.to_m).reshape(-1, 2, 2, 2)
        both = torch.matmul(s.unsqueeze(1), m) + self.target_mean  # (B, 2, 68, 2)
        aligned, canvas = both[:, 0], both[:, 1]
        b_s = torch.matmul(aligned.flatten(1), self.shape_proj) + self.shape_offset
        b_s = torch.minimum(torch.maximum(b_s, -self.shape_limit), self.shape_limit)
        if self.global_appearance:
            b_g = self.appearance.regressor(self.appearance.features(aligned, b_s))
            b_g = torch.minimum(torch.maximum(b_g, -self.app_limit), self.app_limit)
            # float32 matmul, or the int8 basis (MatMulInteger; facesynth.sadm.quantize)
            tex = torch.clamp(self.appearance.deviation(b_g) + self.app_mean, 0.0, 1.0)
            tex = tex.reshape(-1, self.channels, self.n_tex)
        else:
            tex = torch.clamp(self.appearance(aligned, b_s), 0.0, 1.0)
        crop, mask = self.warp(tex, canvas)
        # placement: inverse of the frame -> canvas similarity x_c = R (x - mu) + mu_ref
        sa, sb = ab[:, 2:3], ab[:, 3:4]
        n2 = sa * sa + sb * sb
        inv = torch.matmul(ab[:, 2:], self.to_m[:2, :4]).reshape(-1, 2, 2) / n2.unsqueeze(-1)  # R^-1 = M / |s|^2
        t = mu.transpose(1, 2) - torch.matmul(inv, self.ref_mean)  # (B, 2, 1)
        return crop, mask, torch.cat([inv, t], 2)


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
        "format": FORMAT,
        "regressor": regressor_name(syn),
        "landmark_scheme": "ibug68",
        "n_landmarks": 68,
        "reference_size": list(ref),
        "canvas_size": list(syn.warp.canvas),
        "channels": int(getattr(syn.appearance, "channels", 3)),
        "data_fingerprint": "",
        "output_layout": OUTPUT_LAYOUT,
        "opset": opset,
        "n_scanline_events": syn.warp.n_candidates,
    }
    if isinstance(syn.appearance, GlobalAppearance):
        meta["appearance_basis"] = "float32" if syn.appearance.basis is None else "int8"
    meta.update(metadata or {})
    example = torch.from_numpy(_example_landmarks(syn))
    save_graph(graph, example, path, INPUT_NAME, OUTPUT_NAMES, meta, opset,
               "facesynth synthesis graph: landmarks -> face crop, mask, placement")
    log.info("exported %s (%s regressor, %.1f MB)", path, meta["regressor"], path.stat().st_size / 1e6)
    return path


def save_graph(
    graph: nn.Module, example: torch.Tensor, path: Path, input_name: str, output_names: tuple[str, ...],
    meta: dict, opset: int, doc: str,
) -> None:
    """Trace ``graph`` on ``example`` into ``path`` (written atomically): dynamic batch axis
    on the input and every output, the int32 index pass (its count is recorded as
    ``int32_index_gathers``), producer, ``doc`` and ``meta`` as metadata properties
    (strings, JSON for other values); the file passes ``onnx.checker``."""
    import onnx

    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notices
        with torch.no_grad():
            torch.onnx.export(
                graph, (example,), str(tmp), input_names=[input_name], output_names=list(output_names),
                dynamic_axes={input_name: {0: "batch"}, **{k: {0: "batch"} for k in output_names}},
                opset_version=opset, dynamo=False, do_constant_folding=True,
            )
        model = onnx.load(str(tmp))
        meta.setdefault("int32_index_gathers", int32_indices(model))
        model.producer_name, model.producer_version = "facesynth", __version__
        model.doc_string = doc
        for k, v in meta.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = k, v if isinstance(v, str) else json.dumps(v)
        onnx.checker.check_model(model)
        onnx.save(model, str(tmp))


def _example_landmarks(syn: Synthesizer) -> np.ndarray:
    """(2, 68, 2) plausible frame landmarks (the reference shape, shifted) for tracing."""
    pts = syn.ref_points.detach().cpu().numpy().astype(np.float32)
    return np.stack([pts + 20.0, pts * 1.1 + 5.0]).astype(np.float32)


# ---------------------------------------------------------------------- runs


def load_synthesizer(run_dir: str | os.PathLike) -> tuple[Synthesizer, dict]:
    """Rebuild the :class:`Synthesizer` of a training run directory (the layout of
    :mod:`facesynth.sadm.fit`, written by ``train.py``).

    Returns the synthesizer and metadata for the ONNX file (regressor, data fingerprint, run).
    """
    from facesynth.sadm.fit import load_sadm

    d = Path(run_dir)
    if not d.is_dir():
        raise FacesynthError(f"{d}: training run directory not found")
    sadm = load_sadm(d)
    return sadm.synthesizer(), {"regressor": sadm.name, "data_fingerprint": sadm.model.fingerprint, "run": d.name}


def save_run_synthesizer(run_dir: str | os.PathLike, model, regressor, features: str = "bs", clamp: bool = True) -> Path:
    """Write a face model and SADM regressor as a run directory (for tests and scripts
    that fit outside ``train.py``)."""
    from facesynth.sadm.fit import SADM, SADMConfig, save_sadm

    sadm = SADM(model, regressor, regressor.name, SADMConfig(features=features, clamp_shape=clamp), regressor.config_dict())
    return save_sadm(sadm, run_dir)


DEFAULT_COMPONENTS = 40  # appearance components kept at export (see docs/runtime.md for the measurements)
BASIS_KINDS = ("int8", "float32")
DEFAULT_BASIS = "int8"  # the exported appearance basis (facesynth.sadm.quantize; docs/runtime.md)


def training_landmarks(run_dir: str | os.PathLike) -> np.ndarray:
    """(N, 68, 2) training landmarks of a ``train.py`` run: its ``config.yaml`` names the data
    and the temporal split, which are reloaded (no frames are decoded)."""
    d = Path(run_dir)
    cfg_path = d / "config.yaml"
    if not cfg_path.is_file():
        raise FacesynthError(
            f"{cfg_path}: not found, so the run's training landmarks are unknown; pass --landmarks L.npy "
            "(the training landmarks) or --components 0 (no appearance compression)"
        )
    from omegaconf import OmegaConf

    from facesynth.data import temporal_split
    from facesynth.pipeline import load_data

    cfg = OmegaConf.load(cfg_path)
    seq = load_data(cfg.data, int(cfg.seed))
    rows, _ = temporal_split(len(seq), cfg.data.train_fraction, cfg.data.gap)
    return np.asarray(seq.landmarks[rows], np.float32)


def compress_for_export(
    syn: Synthesizer, landmarks, components: int | None = DEFAULT_COMPONENTS, predicted_variance: float | None = None,
) -> tuple[Synthesizer, dict]:
    """Apply :func:`facesynth.sadm.compress.compress_synthesizer` for export and return the
    metadata that records it. ``components`` 0/None and no ``predicted_variance``, or a
    model with at most ``components`` components: unchanged (``compression: none``).
    ``landmarks`` is an array or a callable returning one (only called when needed)."""
    from facesynth.sadm.compress import compress_synthesizer

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
    from facesynth.sadm.quantize import quantize_synthesizer

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
    syn, meta = load_synthesizer(run_dir)
    lm = functools.cache(lambda: landmarks if landmarks is not None else training_landmarks(run_dir))  # loaded once, if needed
    syn, info = compress_for_export(syn, lm, components, predicted_variance)
    meta.update(info)
    syn, info = quantize_for_export(syn, lm, basis)
    meta.update(info)
    return export_synthesizer(syn, out, meta, opset), syn, meta


def check_export(syn: Synthesizer, path: str | os.PathLike, landmarks: np.ndarray | None = None, tol: float = 1e-4) -> float:
    """Run ``path`` in ONNX Runtime and ``syn`` in torch on the same landmarks.

    Returns the largest absolute crop difference; raises FacesynthError above ``tol`` or
    when the masks differ in more than 0.1% of pixels.
    """
    from facesynth.runtime.renderer import Renderer

    x = _example_landmarks(syn) if landmarks is None else np.asarray(landmarks, np.float32)
    crop, mask, _ = Renderer(path).render(x)
    with torch.no_grad():
        t_crop, t_mask, _ = syn(torch.from_numpy(x))
    both = mask * t_mask.numpy()
    diff = float(np.abs((crop - t_crop.numpy()) * both).max())
    flips = float((mask != t_mask.numpy()).mean())
    if diff > tol or flips > 1e-3:
        raise FacesynthError(f"{path}: ONNX Runtime differs from torch (max |crop diff| {diff:.2e}, mask flips {flips:.2%})")
    return diff
