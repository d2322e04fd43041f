"""Appearance compression for deployment: keep the appearance components whose
*predicted* coefficients vary most.

At batch 1 the synthesis cost is dominated by the (K x C M) appearance matmul (41 MB of
float32 at K = 226, larger than the L3 cache). Many PCA components carry variance in the
training textures that the SADM regressor never predicts (its output for them is almost
constant), so for synthesis from landmarks they can be replaced by their mean prediction:

    b = clamp(regressor(features))                     (N, K) over the training landmarks
    keep = components with the largest var(b[:, k])   (K' of them)
    mean' = mean + mean_n(b[n, drop]) @ P[drop]        (C M,) the dropped part, folded
    texture' = mean' + b[:, keep] @ P[keep]

Clamping acts per component, so the kept coefficients are exactly the full model's; the
only change is that the dropped coefficients are frozen at their training mean. With every
component kept the model is the uncompressed one (``mean' = mean``).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from facesynth.errors import FacesynthError
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer


class SelectOutputs(nn.Module):
    """Fallback: ``regressor(x)[:, keep]`` for regressors without a sliceable read-out layer."""

    def __init__(self, regressor: nn.Module, keep: np.ndarray):
        super().__init__()
        self.inner = regressor
        self.register_buffer("keep", torch.as_tensor(np.asarray(keep, np.int64)))
        self.name = getattr(regressor, "name", type(regressor).__name__)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.inner(x)[:, self.keep]


def select_outputs(regressor: nn.Module, keep: np.ndarray, n_out: int) -> nn.Module:
    """A copy of ``regressor`` that predicts only outputs ``keep`` (in that order).

    Regressors whose last step is affine (linear, poly2, SVR: ``weight``/``coef`` (D_out, .)
    and ``bias`` (D_out,); MLP: last ``nn.Linear``) get their read-out rows sliced, so the
    exported graph computes only K' outputs; others are wrapped in :class:`SelectOutputs`.
    """
    keep_t = torch.as_tensor(np.asarray(keep, np.int64))
    out = copy.deepcopy(regressor)
    net = getattr(out, "net", None)
    if isinstance(net, nn.Sequential) and isinstance(net[-1], nn.Linear) and net[-1].out_features == n_out:
        last = net[-1]
        new = nn.Linear(last.in_features, len(keep_t), bias=last.bias is not None)
        with torch.no_grad():
            new.weight.copy_(last.weight[keep_t])
            if last.bias is not None:
                new.bias.copy_(last.bias[keep_t])
        net[-1] = new
        if hasattr(out, "d_out"):
            out.d_out = int(len(keep_t))
        return out
    names = [k for k in ("weight", "coef", "bias") if isinstance(out._buffers.get(k), torch.Tensor)]
    if "bias" in names and all(out._buffers[k].shape[0] == n_out for k in names):
        for k in names:
            out._buffers[k] = out._buffers[k][keep_t].contiguous()
        return out
    return SelectOutputs(regressor, keep)


def predicted_params(syn: Synthesizer, landmarks: np.ndarray, batch: int = 512) -> np.ndarray:
    """Clamped b_g the synthesizer predicts for (N, P, 2) frame landmarks -> (N, K) float64."""
    app = syn.appearance
    if not isinstance(app, GlobalAppearance):
        raise FacesynthError("appearance compression needs a global (PCA) appearance model")
    x = np.asarray(landmarks, np.float32)
    out = []
    with torch.no_grad():
        for i in range(0, len(x), batch):
            lm = torch.from_numpy(x[i:i + batch])
            out.append(app.params(*syn.encoder(syn.model_landmarks(lm)), lm).double().numpy())
    return np.concatenate(out)


def choose_components(b: np.ndarray, keep: int | None = None, predicted_variance: float | None = None) -> np.ndarray:
    """Indices (sorted by decreasing predicted variance) of the components to keep.

    b : (N, K) predicted coefficients. ``keep``: that many; ``predicted_variance`` q in (0, 1]:
    the fewest components whose predicted variance sums to >= q of the total.
    """
    k_all = b.shape[1]
    var = b.var(0)
    order = np.argsort(-var, kind="stable")
    if (keep is None) == (predicted_variance is None):
        raise FacesynthError("appearance compression: give exactly one of keep=K or predicted_variance=q")
    if keep is not None:
        if not 1 <= int(keep) <= k_all:
            raise FacesynthError(f"appearance compression: components must be in 1..{k_all}, got {keep}")
        n = int(keep)
    else:
        q = float(predicted_variance)
        if not 0.0 < q <= 1.0:
            raise FacesynthError(f"appearance compression: predicted variance must be in (0, 1], got {q}")
        total = float(var.sum())
        if total <= 0:
            n = 1
        else:
            n = min(int(np.searchsorted(np.cumsum(var[order]) / total, q - 1e-12) + 1), k_all)
    return order[:n]


def compress_synthesizer(
    syn: Synthesizer, landmarks: np.ndarray, keep: int | None = None, predicted_variance: float | None = None,
) -> tuple[Synthesizer, dict]:
    """A copy of ``syn`` whose appearance keeps the components of largest predicted variance.

    Parameters
    ----------
    syn : Synthesizer with a :class:`GlobalAppearance`
    landmarks : (N, P, 2) frame landmarks the selection is measured on (the training frames)
    keep, predicted_variance : exactly one: number of components, or the fraction q of the
        total predicted variance to keep

    Returns
    -------
    (Synthesizer, info): info records ``appearance_components_full``, ``appearance_components``,
    ``kept_predicted_variance`` (fraction), ``kept_components`` (indices) and
    ``compression_psnr_vs_full_db``: PSNR (peak 1) of the compressed vs the full texture
    (clipped to [0, 1], reference mask pixels) over ``landmarks``.
    """
    if getattr(syn.appearance, "basis", None) is not None:
        raise FacesynthError("appearance compression: compress before quantizing the basis (this synthesizer is int8)")
    landmarks = np.asarray(landmarks, np.float32)
    if landmarks.ndim != 3 or landmarks.shape[1:] != (syn.n_points, 2):
        raise FacesynthError(f"appearance compression: landmarks must be (N, {syn.n_points}, 2), got {landmarks.shape} "
                             f"(scheme {syn.scheme})")
    landmarks = landmarks[np.isfinite(landmarks).all(axis=(1, 2))]
    if len(landmarks) < 2:
        raise FacesynthError("appearance compression: needs at least 2 finite landmark rows (the training frames)")
    b = predicted_params(syn, landmarks)
    keep_idx = choose_components(b, keep, predicted_variance)
    app = syn.appearance
    k_all = b.shape[1]
    drop = np.setdiff1d(np.arange(k_all), keep_idx)
    comps = app.components.double()
    mean = app.mean.double()
    if len(drop):
        mean = mean + torch.from_numpy(b[:, drop].mean(0)) @ comps[torch.from_numpy(drop)]
    new_app = app.shallow_copy()
    keep_t = torch.from_numpy(keep_idx)
    new_app.regressor = select_outputs(app.regressor, keep_idx, k_all)
    new_app.mean = mean.float()
    new_app.components = app.components[keep_t].contiguous()
    new_app.limit = app.limit[keep_t].contiguous()
    if getattr(app, "gaze", None) is not None and app.gaze.target == "params":  # it predicts the same components
        new_app.gaze = app.gaze.select_outputs(keep_idx)
    out = syn.with_appearance(new_app)
    var = b.var(0)
    info = {
        "appearance_components_full": int(k_all),
        "appearance_components": int(len(keep_idx)),
        "kept_predicted_variance": float(var[keep_idx].sum() / max(var.sum(), 1e-300)),
        "kept_components": [int(i) for i in keep_idx],
        "compression_psnr_vs_full_db": texture_psnr(syn, out, landmarks),
        "compression_frames": int(len(landmarks)),
    }
    return out, info


def texture_psnr(full: Synthesizer, other: Synthesizer, landmarks: np.ndarray, batch: int = 512) -> float:
    """PSNR (dB, peak 1) of ``other``'s reference texture vs ``full``'s over (N, P, 2) landmarks."""
    x = np.asarray(landmarks, np.float32)
    se, n = 0.0, 0
    with torch.no_grad():
        for i in range(0, len(x), batch):
            lm = torch.from_numpy(x[i:i + batch])
            d = (full.texture(lm).double() - other.texture(lm).double())
            se += float((d * d).sum())
            n += d.numel()
    mse = se / max(n, 1)
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))
