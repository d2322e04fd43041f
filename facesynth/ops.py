"""Tensor ops whose ONNX form is fixed by hand (custom ``symbolic`` functions), so that the
stages' torch modules trace to short, standard ONNX graphs. This is the one place where
the stages touch ONNX export specifics; :mod:`facesynth.onnx` traces the modules that use
these ops and the parity tests hold torch eager and ONNX Runtime to the same numbers.

* :func:`pad_by_tensor`: zero padding by pads computed in the graph (one ``Pad``);
* :func:`slice_by_tensor`: a box of the last two axes cut at bounds computed in the graph
  (one ``Slice``; tracing would freeze Python slice bounds into constants);
* :func:`sum4`: the 4-tap sum of a bilinear interpolation (a (1, 4) ``MatMul`` in ONNX,
  whose ``ReduceSum`` over axis 1 is several times slower in ONNX Runtime; a plain sum in
  torch eager, where a BLAS matmul here stalls the thread pool on busy cores);
* :func:`int8_matmul`: ``(round(b * coef_scale) @ codes) * col_scale`` as standard integer
  ops (one ``MatMulInteger``, u8 x s8), exact in torch eager too, and exact in ONNX Runtime on
  every CPU as long as the weight codes stay within ``CODE_LEVELS`` (below).

**Why 7-bit weight codes.** On x86 without VNNI, ONNX Runtime's u8 x s8 kernel multiplies
with ``vpmaddubsw``, which adds *pairs* of u8 x s8 products into a saturating int16. The
coefficient codes travel as u8 ``a + 128`` in [1, 255], so a pair of products reaches
2 * 255 * |q|: with |q| <= 127 that is 64770 and the sum silently clips at 32767 (a wrong
texture, no error); with |q| <= ``CODE_LEVELS`` = 64 (:mod:`facesynth.contract`) it is at
most 32640 and every partial sum is exact. VNNI (``vpdpbusd``) and ARM's dot products widen to int32 first and
are exact either way. ONNX Runtime's quantization guide gives the same advice
(``reduce_range``: 7-bit weights on such CPUs).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from facesynth.contract import COEF_LEVELS, LEGACY_CODE_LEVELS, ZERO_POINT

EXACT_FLOAT32_K = 2**24 // (COEF_LEVELS * LEGACY_CODE_LEVELS) + 1  # 1041: below it a @ q is exact in float32


class _Pad(torch.autograd.Function):
    """Zero padding of a 4-D tensor by a pads *tensor* in ONNX order (begins of the four axes,
    then ends), exported as one ONNX ``Pad`` whose pads are computed in the graph (``F.pad``
    takes Python ints, which tracing would freeze into constants)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, pads: torch.Tensor) -> torch.Tensor:
        p = [int(v) for v in pads.tolist()]
        return F.pad(x, [p[3], p[7], p[2], p[6], p[1], p[5], p[0], p[4]])

    @staticmethod
    def symbolic(g, x, pads):
        return g.op("Pad", x, pads, mode_s="constant")


def pad_by_tensor(x: torch.Tensor, pads: torch.Tensor) -> torch.Tensor:
    """Zero-pad (B, C, H, W) ``x`` by int64 ``pads`` (8,) in ONNX order: begins of the four
    axes, then their ends."""
    return _Pad.apply(x, pads)


class _Slice(torch.autograd.Function):
    """``x[..., y0:y1, x0:x1]`` of a 4-D tensor for an int64 bounds tensor [y0, x0, y1, x1],
    exported as one ONNX ``Slice`` on axes 2 and 3."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        y0, x0, y1, x1 = (int(v) for v in bounds.tolist())
        return x[:, :, y0:y1, x0:x1].clone()

    @staticmethod
    def symbolic(g, x, bounds):
        def const(v):
            return g.op("Constant", value_t=torch.tensor(v))

        starts = g.op("Slice", bounds, const([0]), const([2]))
        ends = g.op("Slice", bounds, const([2]), const([4]))
        return g.op("Slice", x, starts, ends, const([2, 3]))


def slice_by_tensor(x: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) ``x`` cut to rows y0:y1 and columns x0:x1 of int64 ``bounds`` (4,)
    [y0, x0, y1, x1]."""
    return _Slice.apply(x, bounds)


def sum4(ones4: torch.Tensor, prod: torch.Tensor) -> torch.Tensor:
    """Sum (B, 4, N) ``prod`` over axis 1 -> (B, 1, N); ``ones4`` is a (1, 4) tensor of ones."""
    return torch.matmul(ones4, prod) if torch.onnx.is_in_onnx_export() else prod.sum(1, keepdim=True)


class _Int8MatMul(torch.autograd.Function):
    """``(round(b * coef_scale) @ codes) * col_scale``, exported as standard ONNX integer ops
    (Mul, Round, Add, Cast, MatMulInteger, Cast, Mul); torch eager computes the same integers."""

    @staticmethod
    def forward(ctx, b, coef_scale, codes_f, codes, col_scale):
        a = torch.round(b * coef_scale)
        if codes_f.shape[0] >= EXACT_FLOAT32_K:  # partial sums may pass 2^24: sum exactly in float64
            return (torch.matmul(a.double(), codes_f.double()) * col_scale.double()).to(b.dtype)
        return torch.matmul(a, codes_f) * col_scale

    @staticmethod
    def symbolic(g, b, coef_scale, codes_f, codes, col_scale):
        a = g.op("Round", g.op("Mul", b, coef_scale))
        zp = g.op("Constant", value_t=torch.tensor(ZERO_POINT, dtype=torch.uint8))
        a_u8 = g.op("Cast", g.op("Add", a, g.op("Constant", value_t=torch.tensor(float(ZERO_POINT)))), to_i=2)  # UINT8
        acc = g.op("MatMulInteger", a_u8, codes, zp)
        return g.op("Mul", g.op("Cast", acc, to_i=1), col_scale)  # FLOAT


def int8_matmul(b: torch.Tensor, coef_scale: torch.Tensor, codes_f: torch.Tensor, codes: torch.Tensor,
                col_scale: torch.Tensor) -> torch.Tensor:
    """(B, K) coefficients -> (B, D): ``(round(b * coef_scale) @ codes) * col_scale`` with
    ``codes`` int8 (K, D), ``codes_f`` the same as float32, scales (K,) and (D,)."""
    return _Int8MatMul.apply(b, coef_scale, codes_f, codes, col_scale)
