"""Int8 appearance basis for deployment: the (K x C M) appearance matmul in 8-bit integers.

At batch 1 the appearance reconstruction ``b_g @ P`` reads the whole (K, C M) basis every
frame: 7 MB of float32 at K = 40 on a 480x480 clip's face, more than a core's L2 cache, so
its cost swings with whatever else shares the L3 (the measurements are in docs/runtime.md).
Stored as int8 it is 1.76 MB, and ONNX Runtime runs it as one standard ``MatMulInteger``
(u8 activations x s8 weights): ``vpdpbusd`` on x86 with VNNI, ``vpmaddubsw`` on x86 without
it, dot-product instructions on ARM.

Static symmetric quantization with a known input range (Jacob et al., "Quantization and
Training of Neural Networks for Efficient Integer-Arithmetic-Only Inference", CVPR 2018):

* coefficients: b_g is clamped to +-limit_k (3 sigma of component k), so
  ``a_k = round(127 b_k / limit_k)`` is an integer in [-127, 127] (no per-frame scale);
* basis: ``W = diag(limit / 127) P`` is each component's contribution per coefficient step,
  quantized per texture element (column) to **7-bit codes**: ``s_n = max_k |W_kn| / 64``,
  ``q_kn = round(W_kn / s_n)`` in [-64, 64] (:data:`facesynth.contract.CODE_LEVELS`). Full 8-bit
  codes would overflow the saturating int16 pair sums of the non-VNNI x86 kernel and give
  wrong textures there without any error (:mod:`facesynth.ops` has the arithmetic);
* texture: ``mean + s * (a @ q)``. ``a @ q`` is exact in int32 on every CPU (and in float32:
  every partial sum is an integer below 2^24 for K <= 1040; torch sums in float64 above), so
  the torch graph (:class:`Int8Basis` in eager mode) and ONNX Runtime compute the same numbers.

The cost is two rounding errors of at most half a step each, measured by
:func:`quantize_synthesizer` as the PSNR of the int8 vs the float texture over the
training landmarks (recorded in the exported file, with the largest |code| as
``appearance_code_levels``, which the runtime reads to recognise older, saturating files).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from facesynth.contract import CODE_LEVELS, COEF_LEVELS
from facesynth.errors import FacesynthError
from facesynth.ops import int8_matmul
from facesynth.sadm.compress import texture_psnr
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer


def quantize_columns(weights: np.ndarray, levels: int = CODE_LEVELS) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric per-column int8 quantization.

    Parameters
    ----------
    weights : (K, D) float array
    levels : codes in [-levels, levels] (default the int16-safe :data:`facesynth.contract.CODE_LEVELS`)

    Returns
    -------
    codes : (K, D) int8 in [-levels, levels]
    scale : (D,) float32, ``weights ~= codes * scale`` (a column of zeros gets scale 1)
    """
    if not 1 <= int(levels) <= 127:
        raise FacesynthError(f"int8 quantization: levels must be in [1, 127], got {levels}")
    w = np.asarray(weights, np.float64)
    if w.ndim != 2 or not np.isfinite(w).all():
        raise FacesynthError(f"int8 quantization: weights must be a finite 2-D array, got shape {w.shape}")
    scale = np.abs(w).max(0) / int(levels)
    scale = np.where(scale > 0, scale, 1.0).astype(np.float32)
    codes = np.clip(np.rint(w / scale.astype(np.float64)), -int(levels), int(levels)).astype(np.int8)
    return codes, scale


class Int8Basis(nn.Module):
    """Appearance deviation from int8 codes: b (B, K) clamped coefficients -> (B, D).

    Buffers: ``coef_scale`` (K,) = 127 / limit, ``codes`` (K, D) int8 in [-levels, levels],
    ``codes_f`` the same codes as float32 (torch's matmul), ``col_scale`` (D,). Build with
    :meth:`from_basis`; ``levels`` is the code range it was quantized to.
    """

    def __init__(self, coef_scale: torch.Tensor, codes: torch.Tensor, col_scale: torch.Tensor):
        super().__init__()
        self.register_buffer("coef_scale", coef_scale.float())
        self.register_buffer("codes", codes.to(torch.int8))
        self.register_buffer("codes_f", codes.float())
        self.register_buffer("col_scale", col_scale.float())

    @property
    def levels(self) -> int:
        """The largest |code| (the range the basis was quantized to is at least this)."""
        return int(self.codes.abs().max()) if self.codes.numel() else 0

    @classmethod
    def from_basis(cls, components: np.ndarray, limit: np.ndarray, levels: int = CODE_LEVELS) -> "Int8Basis":
        """Quantize a (K, D) basis whose coefficients are clamped to +-``limit`` (K,) (finite,
        > 0) to codes in [-``levels``, ``levels``]."""
        lim = np.asarray(limit, np.float64)
        if not (np.isfinite(lim).all() and (lim > 0).all()):
            raise FacesynthError("int8 appearance basis: needs finite, positive clamping limits for every "
                                 "component (the model was built with clamping off); export with --basis float32")
        codes, scale = quantize_columns(np.asarray(components, np.float64) * (lim / COEF_LEVELS)[:, None], levels)
        return cls(torch.from_numpy((COEF_LEVELS / lim).astype(np.float32)), torch.from_numpy(codes), torch.from_numpy(scale))

    def scaled(self, b: torch.Tensor) -> torch.Tensor:
        """(B, K) the coefficients in code units, ``b * coef_scale``: what :meth:`forward` rounds
        to codes (the int8 parity contract, :data:`facesynth.contract.FLOAT_PARITY_TOL`, is about
        the values that lie on a rounding tie)."""
        return b * self.coef_scale

    def dequantized(self) -> torch.Tensor:
        """(K, D) float64 basis this module applies to unrounded coefficients."""
        return self.codes_f.double() * self.col_scale.double() / self.coef_scale.double()[:, None]

    def forward(self, b: torch.Tensor) -> torch.Tensor:
        return int8_matmul(b, self.coef_scale, self.codes_f, self.codes, self.col_scale)


def quantize_synthesizer(syn: Synthesizer, landmarks: np.ndarray | None = None,
                         levels: int = CODE_LEVELS) -> tuple[Synthesizer, dict]:
    """A copy of ``syn`` whose appearance basis is int8 (:class:`Int8Basis`).

    Parameters
    ----------
    syn : Synthesizer with a :class:`GlobalAppearance` (compressed or not) and finite limits
    landmarks : (N, P, 2) frame landmarks (the synthesizer's scheme) to measure the effect on (the training frames), optional
    levels : weight codes in [-levels, levels]; the default is exact on every CPU (a larger
      range reproduces older files, for comparison: ``bench/export/int8.py``)

    Returns
    -------
    (Synthesizer, info): info records ``appearance_basis`` ("int8"), ``appearance_basis_bytes``
    and, with landmarks, ``quantization_psnr_vs_float_db``: PSNR (peak 1) of the int8 vs the
    float texture (clipped to [0, 1]) over them.
    """
    app = syn.appearance
    if not isinstance(app, GlobalAppearance):
        raise FacesynthError("int8 appearance basis: needs a global (PCA) appearance model")
    if app.basis is not None:
        raise FacesynthError("int8 appearance basis: the synthesizer is already quantized")
    basis = Int8Basis.from_basis(app.components.double().numpy(), app.limit.double().numpy(), levels)
    new_app = app.shallow_copy()
    new_app.basis = basis
    out = syn.with_appearance(new_app)
    info = {"appearance_basis": "int8", "appearance_basis_bytes": int(basis.codes.numel())}
    if landmarks is not None:
        lm = np.asarray(landmarks, np.float32)
        if lm.ndim != 3 or lm.shape[1:] != (syn.n_points, 2):
            raise FacesynthError(f"int8 appearance basis: landmarks must be (N, {syn.n_points}, 2), got {lm.shape} "
                                 f"(scheme {syn.scheme})")
        lm = lm[np.isfinite(lm).all(axis=(1, 2))]
        if len(lm):
            info["quantization_psnr_vs_float_db"] = texture_psnr(syn, out, lm)
            info["quantization_frames"] = int(len(lm))
    return out, info
