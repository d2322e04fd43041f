"""ONNX export of ERI synthesis for one target face (torch side; the runtime is torch-free).

    faps (B, 36) float32 -> crop (B, 3, Hc, Wc) in [0, 1], mask (B, 1, Hc, Wc),
                            placement (B, 2, 3) crop px -> the target's frame px

:class:`EriGraph` computes what :class:`facesynth.eri.synthesis.EriSynthesizer` computes in
steps 2-4 (``EriSynthesizer.textures`` + ``warp(positions)``; the parity tests hold it to
1e-4), with everything that depends only on the target face baked in as constants:

* step 1 (B_temp, the target's neutral image warped to the model geometry, (3, M)) and the
  edge confidence of the ratios (:func:`facesynth.eri.ratio.edge_confidence`);
* the FAP -> landmark map. :func:`facesynth.eri.faps.faps_to_landmarks` is *linear* in the
  FAPs for a fixed neutral face (FAP displacements along the face axes, then a fixed
  thin-plate-spline interpolation), so landmarks = neutral + J f with the exact Jacobian
  J (136, 36) = :func:`facesynth.eri.faps.fap_displacements` of the identity, in float64;
* the forehead points: they follow the head pose fitted on ``RIGID_FAP``, which the
  FAPs never move (checked at export), so they are the neutral face's.

The graph: SVR kernel expansion of the chosen variant (:class:`facesynth.eri.driving.SVRBank`
as tensor ops: standardise, RBF or linear kernel against the support vectors, dual
weights), clamp to +-``clamp_k`` sqrt(eigenvalue), eigenERI reconstruction, multiplier
(log domain, edge confidence, brightening cap, as ``to_multiplier``; ``raw`` skips the
guards), B' = R' (B_temp + eps) - eps, landmarks, the least-squares similarity onto the
model geometry (closed form, as :func:`facesynth.eri.geometry.to_canvas`), and the
piecewise-affine warp :class:`facesynth.model.warp.ToTarget`.

Compositing into the frame (OpenCV warpAffine + feathering) stays outside the graph, in
:class:`facesynth.runtime.EriRenderer` (the same :func:`facesynth.compositing.composite` as
``EriSynthesizer.render``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from facesynth import __version__
from facesynth.contract import ERI_FORMAT, ERI_INPUT, ERI_METADATA_KEYS, ERI_OUTPUT_LAYOUT, LANDMARK_SCHEME, OPSET, OUTPUT_NAMES
from facesynth.eri.faps import FAP_NAMES, N_FAPS, fap_displacements, faps_to_landmarks
from facesynth.eri.geometry import to_canvas
from facesynth.eri.model import EriModel
from facesynth.eri.ratio import edge_confidence
from facesynth.eri.synthesis import EriSynthesizer
from facesynth.errors import FacesynthError
from facesynth.landmarks import N_LANDMARKS, RIGID_FAP
from facesynth.model.warp import ToTarget, candidate_spans
from facesynth.onnx.common import SimilarityAlignment, check_parity, save_graph
from facesynth.provenance import array_fingerprint
from facesynth.runtime.eri import EriRenderer

METADATA_KEYS = ERI_METADATA_KEYS  # every file carries these (facesynth.contract)


def export_spans(syn: EriSynthesizer, faps: np.ndarray | None = None, safety: float = 1.5) -> np.ndarray:
    """Warp candidate spans (T, 2) for a graph that must serve any plausible FAP vector: the
    model's spans and those of the target driven by ``faps`` (default: the support vectors
    of every SVR variant, i.e. training FAPs, plus zero), times ``safety``."""
    if faps is None:
        banks = syn.model.regressors.values()
        faps = np.concatenate([np.zeros((1, N_FAPS))] + [(b.sv * b.x_std + b.x_mean).numpy() for b in banks])
    canvas = to_canvas(syn.extend(faps_to_landmarks(syn.neutral, faps)), syn.model.reference.points, syn.pad)[0]
    return np.maximum(syn.model.span, candidate_spans(syn.model.reference, canvas, safety))


class EriGraph(nn.Module):
    """The export form of an :class:`EriSynthesizer` (its target face baked in).

    Forward
    -------
    faps : (B, 36) float32 MPEG-4 FAPs (``FAP_NAMES`` order, FAPU units)
    returns : crop (B, 3, Hc, Wc), mask (B, 1, Hc, Wc), placement (B, 2, 3)
    """

    def __init__(self, syn: EriSynthesizer, span: np.ndarray | None = None):
        super().__init__()
        m, cfg = syn.model, syn.model.config
        self._dedupe_support_vectors(m.regressors[syn.variant])
        self.log_ratios, self.raw = bool(cfg.log), bool(syn.raw)
        self.eps, self.n_pix = float(cfg.eps), int(m.n_pixels)
        self.lo = 1.0 / cfg.clip
        self.hi = cfg.clip if syn.raw else min(cfg.clip, cfg.max_brighten or cfg.clip)
        self.register_buffer("limit", torch.from_numpy((cfg.clamp_k * np.sqrt(m.pca.eigenvalues)).astype(np.float32)))
        self.register_buffer("components", torch.from_numpy(np.asarray(m.pca.components, np.float32)))
        self.register_buffer("mean", torch.from_numpy(np.asarray(m.pca.mean, np.float32)).reshape(1, 3, -1))
        conf = edge_confidence(torch.from_numpy(m.neutral_texture), m.sampler(), cfg.edge_tau)
        self.register_buffer("confidence", conf.float().reshape(1, 1, -1))
        self.register_buffer("base_eps", (syn.base.float() + self.eps).unsqueeze(0))  # (1, 3, M)
        # landmarks = neutral + faps @ J^T, J exact in float64; the geometry (landmarks, the
        # similarity onto the canvas, the placement) runs in float64 (a few hundred values
        # per frame) so the warp gets the float32 rounding of the exact canvas landmarks, as
        # the torch path does: float32 canvas coordinates of ~400 px carry 3e-5 px of
        # rounding that sharp texture edges turn into ~1e-4 colour differences
        jac = fap_displacements(syn.neutral, np.eye(N_FAPS)).reshape(N_FAPS, 2 * N_LANDMARKS)  # row i = d landmarks / d f_i
        if np.abs(jac.reshape(N_FAPS, N_LANDMARKS, 2)[:, list(RIGID_FAP)]).max() > 0:
            raise FacesynthError("FAPs move the rigid points; the forehead cannot be baked into the export")
        self.register_buffer("jacobian", torch.from_numpy(jac))
        self.register_buffer("neutral", torch.from_numpy(syn.neutral.reshape(1, 2 * N_LANDMARKS).astype(np.float64)))
        forehead = syn.extend(syn.neutral[None])[0, N_LANDMARKS:]  # (F, 2): the neutral's (head pose = identity)
        self.register_buffer("forehead", torch.from_numpy(np.ascontiguousarray(forehead, np.float64)).unsqueeze(0))
        # closed-form least-squares similarity onto the model geometry (as to_canvas), in float64
        self.align = SimilarityAlignment([m.reference.points], [syn.pad], dtype=torch.float64)
        span = export_spans(syn) if span is None else np.asarray(span)
        self.warp = ToTarget(m.reference, span, syn.canvas)

    def _dedupe_support_vectors(self, b) -> None:
        """The K machines of the bank share their support vectors (rows of the same training
        FAPs): evaluate the kernel once per *distinct* vector (U rows) and sum the dual
        weights of each machine per vector: (B, U) @ (U, K) instead of (B, sum_k n_k) @
        (sum_k n_k, K): far fewer rows (figures in docs/eri.md)."""
        sv, inverse = np.unique(b.sv.numpy().astype(np.float64), axis=0, return_inverse=True)
        w = np.zeros((len(sv), b.weights.shape[1]))
        np.add.at(w, inverse.reshape(-1), b.weights.numpy().astype(np.float64))
        self.rbf, self.gamma = b.kernel != "linear", float(b.gamma)
        self.n_support_vectors, self.n_distinct = int(len(b.sv)), int(len(sv))
        svt = torch.from_numpy(sv.T.astype(np.float32))
        self.register_buffer("svr_scale", (1.0 / b.x_std).reshape(1, -1))
        self.register_buffer("svr_shift", (-b.x_mean / b.x_std).reshape(1, -1))
        if self.rbf:  # exp(-g |z - s|^2) = exp(2g z.s - g |s|^2) exp(-g |z|^2)
            self.register_buffer("sv_t", 2.0 * self.gamma * svt)
            self.register_buffer("sv_norm", -self.gamma * (svt * svt).sum(0, keepdim=True))
            self.register_buffer("svr_weights", torch.from_numpy(w.astype(np.float32)))
        else:  # linear kernel: one (D, K) matrix
            self.register_buffer("svr_weights", torch.from_numpy((sv.T @ w).astype(np.float32)))
        self.register_buffer("svr_out_scale", b.y_scale.reshape(1, -1).clone())
        self.register_buffer("svr_out_shift", (b.intercept * b.y_scale + b.y_mean).reshape(1, -1))

    def coefficients(self, faps: torch.Tensor) -> torch.Tensor:
        """The SVR bank as a kernel expansion over distinct support vectors: (B, 36) -> (B, K)."""
        z = faps * self.svr_scale + self.svr_shift
        if self.rbf:
            arg = torch.matmul(z, self.sv_t) + self.sv_norm - self.gamma * (z * z).sum(1, keepdim=True)
            out = torch.matmul(torch.exp(torch.clamp(arg, max=0.0)), self.svr_weights)
        else:
            out = torch.matmul(z, self.svr_weights)
        return out * self.svr_out_scale + self.svr_out_shift

    def textures(self, faps: torch.Tensor) -> torch.Tensor:
        """Steps 2-3: (B, 36) FAPs -> B' (B, 3, M)."""
        b = self.coefficients(faps)
        b = torch.minimum(torch.maximum(b, -self.limit), self.limit)
        vals = torch.matmul(b, self.components).reshape(-1, 3, self.n_pix) + self.mean
        if not self.raw:
            vals = vals * self.confidence if self.log_ratios else 1.0 + (vals - 1.0) * self.confidence
        r = torch.exp(vals) if self.log_ratios else vals
        r = torch.clamp(r, self.lo, self.hi)
        return torch.clamp(r * self.base_eps - self.eps, 0.0, 1.0)

    def forward(self, faps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        tex = self.textures(faps)
        lm = (torch.matmul(faps.double(), self.jacobian) + self.neutral).reshape(-1, N_LANDMARKS, 2)  # float64
        pts = torch.cat([lm, self.forehead + lm[:, :1] * 0.0], 1)  # (B, P, 2)
        canvas, ab, mu = self.align(pts)
        crop, mask = self.warp(tex, canvas[:, 0].float())
        return crop, mask, self.align.placement(ab, mu, 0).float()


def export_eri(
    syn: EriSynthesizer, path: str | os.PathLike, metadata: dict | None = None, opset: int = OPSET,
    span: np.ndarray | None = None,
) -> Path:
    """Export ``syn`` (model + target face + variant + raw flag) to one ONNX file, written
    atomically, with a dynamic batch axis and the metadata of :data:`METADATA_KEYS`.

    Parameters
    ----------
    syn : EriSynthesizer
    path : output ``.onnx`` file
    metadata : extra metadata properties (strings, or JSON for other values)
    opset : int
    span : (T, 2) warp spans (default :func:`export_spans`)
    """
    path = Path(path)
    graph = EriGraph(syn, span).eval()
    m = syn.model
    meta = {
        "facesynth_version": __version__, "format": ERI_FORMAT, "kind": "eri", "driver": syn.variant,
        "raw_ratios": bool(syn.raw), "n_faps": N_FAPS, "fap_names": list(FAP_NAMES), "landmark_scheme": LANDMARK_SCHEME,
        "reference_size": list(m.reference.size), "canvas_size": list(syn.canvas),
        "frame_size": [int(syn.image.shape[1]), int(syn.image.shape[0])], "channels": 3, "data_fingerprint": m.fingerprint,
        "target_fingerprint": array_fingerprint(syn.image, syn.neutral), "feather": float(m.config.feather),
        "eigeneri_components": int(m.pca.n_components), "support_vectors": graph.n_support_vectors,
        "distinct_support_vectors": graph.n_distinct,
        "output_layout": ERI_OUTPUT_LAYOUT, "opset": opset, "n_scanline_events": graph.warp.n_scanline_events,
    }
    meta.update(metadata or {})
    example = torch.zeros(2, N_FAPS)
    example[1] = torch.linspace(-50, 50, N_FAPS)
    save_graph(graph, example, path, ERI_INPUT, OUTPUT_NAMES, meta, opset,
               "facesynth ERI graph: MPEG-4 FAPs -> target face crop, mask, placement")
    return path


def export_eri_run(
    run_dir: str | os.PathLike, out: str | os.PathLike, image: np.ndarray, landmarks: np.ndarray,
    variant: str | None = None, raw: bool = False, opset: int = OPSET,
) -> tuple[Path, EriSynthesizer, dict]:
    """``facesynth export RUN --target ...``: the run's ERI model for one target face
    (uint8 (H, W, 3) image and its (68, 2) landmarks). Returns the file, the synthesizer
    and the metadata written besides the standard keys."""
    d = Path(run_dir)
    if not d.is_dir():
        raise FacesynthError(f"{d}: training run directory not found")
    try:
        model = EriModel.load(d)
    except FacesynthError as exc:
        raise FacesynthError(f"{d}: no ERI model to export with --target ({exc})") from None
    if variant is not None and variant not in model.regressors:
        raise FacesynthError(f"ERI model has no regressor {variant!r}; it has {sorted(model.regressors)}")
    syn = EriSynthesizer(model, image, landmarks, variant, raw)
    meta = {"run": d.name, "driver": syn.variant, "raw_ratios": bool(raw)}
    return export_eri(syn, out, meta, opset), syn, meta


def torch_reference(syn: EriSynthesizer, faps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``EriSynthesizer``'s own torch path, in the graph's layout: crop (B, 3, Hc, Wc),
    mask (B, 1, Hc, Wc), placement (B, 2, 3)."""
    faps = np.asarray(faps, np.float32)
    crop, mask, place = syn.warp(syn.textures(faps), syn.positions(faps))
    return crop.transpose(0, 3, 1, 2), mask[:, None], place.astype(np.float32)


def check_eri_export(syn: EriSynthesizer, path: str | os.PathLike, faps: np.ndarray | None = None, tol: float = 1e-4) -> float:
    """Run ``path`` in ONNX Runtime and ``syn`` in torch on the same FAPs (default: the
    support vectors of the exported variant). Returns the largest absolute crop difference;
    raises FacesynthError above ``tol``, on NaN, or when masks differ in more than 0.1% of
    pixels (:func:`facesynth.onnx.common.check_parity`)."""
    if faps is None:
        b = syn.model.regressors[syn.variant]
        faps = (b.sv[:8] * b.x_std + b.x_mean).numpy()
    crop, mask, _ = EriRenderer(path).render(faps)
    t_crop, t_mask, _ = torch_reference(syn, faps)
    return check_parity(path, (crop, mask), (t_crop, t_mask), tol)
