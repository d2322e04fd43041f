"""What the synthesis and ERI graphs share: the closed-form similarity alignment, the
writer (trace, int32 index pass, metadata, checker) and the ONNX Runtime vs torch parity
check."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from facesynth import __version__
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path
from facesynth.onnx.passes import int32_indices

# [a, b] -> row-major M = [[a, b], [-b, a]], so that aligned = s @ M
_TO_M = ((1.0, 0.0, 0.0, 1.0), (0.0, 1.0, -1.0, 0.0))


class SimilarityAlignment(nn.Module):
    """Least-squares 2D similarities (rotation, scale, translation; Umeyama) of a batch of
    point sets onto T fixed targets, in closed form: one matmul for all targets.

    For centred points s and a centred target d, the similarity's [a, b] is
    ``(s . d, s . perp(d)) / |s|^2``; the T targets' columns form one (2P, 2T) matrix.

    Parameters
    ----------
    targets : T arrays (P, 2), the target point sets
    offsets : T (2,) offsets added to the targets' means (e.g. a canvas padding), optional
    dtype : torch dtype of the constants (and of the computation)

    Forward
    -------
    points : (B, P, 2)
    returns : aligned (B, T, P, 2), ab (B, 2T) = [a_t, b_t] per target, mu (B, 1, 2) the points' mean
    """

    def __init__(self, targets: Sequence[np.ndarray], offsets: Sequence[np.ndarray] | None = None,
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        cols, means = [], []
        for d in targets:
            d = np.asarray(d, np.float64)
            mu = d.mean(0)
            dc = d - mu
            cols += [dc.reshape(-1), np.stack([dc[:, 1], -dc[:, 0]], -1).reshape(-1)]  # s . perp = s_x d_y - s_y d_x
            means.append(mu)
        means = np.stack(means) + (0.0 if offsets is None else np.asarray(offsets, np.float64))
        n = len(targets)
        self.n_targets = n
        self.register_buffer("basis", torch.from_numpy(np.stack(cols, 1)).to(dtype))  # (2P, 2T)
        to_m = torch.tensor(_TO_M, dtype=torch.float64)
        self.register_buffer("to_m", torch.block_diag(*[to_m] * n).to(dtype))  # (2T, 4T)
        self.register_buffer("target_mean", torch.from_numpy(means).to(dtype).reshape(n, 1, 2))

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mu = points.mean(1, keepdim=True)  # (B, 1, 2)
        s = points - mu
        var = (s * s).flatten(1).sum(1, keepdim=True)  # (B, 1)
        ab = torch.matmul(s.flatten(1), self.basis) / var  # (B, 2T)
        m = torch.matmul(ab, self.to_m).reshape(-1, self.n_targets, 2, 2)
        return torch.matmul(s.unsqueeze(1), m) + self.target_mean, ab, mu

    def placement(self, ab: torch.Tensor, mu: torch.Tensor, target: int) -> torch.Tensor:
        """(B, 2, 3) affine map from target ``target``'s pixels back to the points' frame:
        the inverse of ``x_t = R (x - mu) + mean_t`` (``R^-1 = M / |s|^2``)."""
        abt = ab[:, 2 * target:2 * target + 2]
        n2 = (abt * abt).sum(1, keepdim=True).unsqueeze(-1)  # (B, 1, 1)
        inv = torch.matmul(abt, self.to_m[:2, :4]).reshape(-1, 2, 2) / n2
        t = mu.transpose(1, 2) - torch.matmul(inv, self.target_mean[target].reshape(1, 2, 1))
        return torch.cat([inv, t], 2)


def save_graph(
    graph: nn.Module, example: torch.Tensor | tuple[torch.Tensor, ...], path: Path, input_name: str | tuple[str, ...],
    output_names: tuple[str, ...], meta: dict, opset: int, doc: str,
) -> None:
    """Trace ``graph`` on ``example`` (one input tensor, or a tuple for ``input_name`` a tuple
    of names) into ``path`` (written atomically): dynamic batch axis on the first input and
    every output, the int32 index pass (its count is recorded as ``int32_index_gathers``),
    producer, ``doc`` and ``meta`` as metadata properties (strings, JSON for other values);
    the file passes ``onnx.checker``."""
    import onnx  # heavy: imported when a graph is written

    names = [input_name] if isinstance(input_name, str) else list(input_name)
    example = (example,) if isinstance(example, torch.Tensor) else tuple(example)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        # torch.onnx.export(dynamo=False) is the TorchScript exporter, deprecated in torch 2.9+; the
        # dynamo exporter cannot trace the warp's custom symbolics (facesynth.ops), so it stays
        warnings.simplefilter("ignore")
        with torch.no_grad():
            torch.onnx.export(
                graph, example, str(tmp), input_names=names, output_names=list(output_names),
                dynamic_axes={names[0]: {0: "batch"}, **{k: {0: "batch"} for k in output_names}},
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


def check_parity(path, onnx_out: tuple[np.ndarray, np.ndarray], torch_out: tuple[np.ndarray, np.ndarray],
                 tol: float | np.ndarray = 1e-4) -> float:
    """Compare (crop, mask) from ONNX Runtime with torch's: returns the largest absolute crop
    difference where both masks are set; raises FacesynthError where a frame's difference
    passes ``tol`` (a number, or (B,) one per frame), when the masks differ in more than 0.1%
    of pixels, or when either holds NaN (NaN never passes)."""
    crop, mask = onnx_out
    t_crop, t_mask = torch_out
    per_frame = np.abs((crop - t_crop) * mask * t_mask).reshape(len(crop), -1).max(1)
    flips = float((mask != t_mask).mean())
    over = ~(per_frame <= tol)
    if over.any() or not flips <= 1e-3:
        where = ""
        if over.any():
            f = int(np.flatnonzero(over)[0])
            where = f", frame {f}: {per_frame[f]:.2e} > {float(np.broadcast_to(tol, per_frame.shape)[f]):.2e}"
        raise FacesynthError(f"{path}: ONNX Runtime differs from torch (max |crop diff| {per_frame.max():.2e}{where}, "
                             f"mask flips {flips:.2%})")
    return float(per_frame.max())
