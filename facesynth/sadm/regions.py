"""The face's parts in a face model's reference frame, and SADM's per-region shrinkage
towards the mean texture ("never worse than the mean").

The parts are those of :func:`facesynth.landmarks.face_region_masks` (eyes, mouth interior,
lips, brows, rest), drawn from the iBUG-68 view of the reference points, so that evaluation
in the frame, this shrinkage and the ceiling study cut the face the same way.

Shrinkage: where the landmarks say little about a part (gaze in the eyes, tongue and teeth
in the mouth interior), a regressor's prediction there can be further from the held-out
texture than the mean texture is. Per part r, the prediction's deviation from the mean is
scaled by w_r in [0, 1]::

    texture'[r] = mean[r] + w_r (texture[r] - mean[r])

chosen on held-out training frames: by default the training segment is cut into 5
contiguous blocks, each predicted by a SADM fitted on the others, and per block b the
least-squares blend

    w_rb = clip( sum (p - m)(t - m) / sum (p - m)^2 , 0, 1 )      over block b's pixels of r

(p: prediction, t: true texture, m: mean); w_r = max_b w_rb, so a part is shrunk only as
far as every block agrees (``sadm.shrink_folds=0``: one least-squares weight on the
validation slice instead). Why the maximum: docs/sadm.md measures the pooled weight
and the validation slice's, both of which shrank parts that the test segment needed. w_r = 1 leaves the part as predicted; w_r = 0
renders the mean there. Since the scaling is per texture column it folds into the
appearance basis (its columns scaled) and the gaze path's texture correction, so the
synthesis graph, its ONNX export, compression and the int8 basis are unchanged.
"""

from __future__ import annotations

import numpy as np
import torch

from facesynth.errors import FacesynthError
from facesynth.landmarks import FACE_REGIONS, MOUTH_CLOSED, face_region_masks, get_scheme, ibug68_view, mouth_open


def reference_regions(model) -> dict[str, np.ndarray]:
    """bool (M,) masks over ``model``'s reference-frame mask pixels, one per part of
    :data:`FACE_REGIONS` that has pixels there (disjoint, covering all M; a reference shape
    with a closed mouth has no ``mouth_interior``)."""
    h, w = model.reference.size
    index = model.sampler().mask_index.numpy()
    inside = np.zeros(h * w, bool)
    inside[index] = True
    pts = ibug68_view(np.asarray(model.reference.points, np.float64))
    masks = face_region_masks(pts, (h, w), within=inside.reshape(h, w))
    return {name: m.reshape(-1)[index] for name, m in masks.items() if m.any()}


def closed_mouths(landmarks: np.ndarray) -> np.ndarray:
    """bool (N,): which of (N, P, 2) landmark sets (any registered scheme) have a closed mouth
    (:func:`~facesynth.landmarks.mouth_open` of their iBUG-68 view at most ``MOUTH_CLOSED``)."""
    return mouth_open(ibug68_view(np.asarray(landmarks, np.float64))) <= MOUTH_CLOSED


def frame_regions(model, landmarks: np.ndarray) -> dict[str, np.ndarray]:
    """bool (N, M) per part, for N frames' textures in ``model``'s reference frame: the parts of
    :func:`reference_regions`, but in a frame whose mouth is closed (its (N, P, 2) ``landmarks``'
    :func:`~facesynth.landmarks.mouth_open` at most ``MOUTH_CLOSED``) the mouth interior's pixels
    count as lips, as :func:`~facesynth.landmarks.face_region_masks` cuts that frame itself.
    Parts with no pixel in any frame are left out."""
    parts = reference_regions(model)
    n = len(landmarks)
    out = {name: np.repeat(m[None], n, 0) for name, m in parts.items()}
    if "mouth_interior" in parts:
        closed = closed_mouths(landmarks)
        out.setdefault("lips", np.zeros_like(out["mouth_interior"]))[closed] |= parts["mouth_interior"]
        out["mouth_interior"][closed] = False
    return {name: m for name, m in out.items() if m.any()}


def pixel_errors(a: np.ndarray, b: np.ndarray, n_channels: int) -> np.ndarray:
    """float64 (N, M): squared differences of (N, C M) textures in [0, 1] (clipped), summed
    over the C channels of each pixel."""
    d = (np.clip(a, 0, 1) - np.clip(b, 0, 1)).astype(np.float64).reshape(len(a), n_channels, -1)
    return (d * d).sum(1)


def masked_psnr01(errors: np.ndarray, mask: np.ndarray, n_channels: int) -> float:
    """PSNR (dB, peak 255 on [0, 1] textures) over the pixels of a bool (N, M) ``mask`` of
    :func:`pixel_errors`' (N, M) ``errors``."""
    mse = float(errors[mask].sum()) / (n_channels * int(mask.sum()))
    return float(10 * np.log10(1.0 / max(mse, 1e-20)))


def column_weights(model, weights: dict[str, float]) -> np.ndarray:
    """float32 (C M,) per texture column (channel-major): the weight of its part (1 for parts
    not in ``weights``)."""
    per_pixel = np.ones(model.n_pixels, np.float32)
    for name, m in reference_regions(model).items():
        per_pixel[m] = float(weights.get(name, 1.0))
    return np.tile(per_pixel, model.n_channels)


def shrink_appearance(app, model, weights: dict[str, float]):
    """``app`` (a freshly built :class:`~facesynth.sadm.synthesis.GlobalAppearance` of
    ``model``) with each part's deviation from the mean scaled by its weight: the basis's
    columns scaled (mean + w (b_g P) = mean + b_g (P w)), and a gaze path that corrects the
    texture replaced by a scaled copy (the shared one is left untouched). Returns ``app``."""
    cols = torch.from_numpy(column_weights(model, weights))
    gaze = app.gaze
    if gaze is not None and gaze.target != "params":
        app.gaze = type(gaze)(get_scheme(gaze.features.scheme), gaze.mu, gaze.sd, gaze.weight * cols, gaze.bias * cols,
                              gaze.alpha, gaze.target).eval()
    app.components = app.components * cols
    return app


def _ls_weight(d: np.ndarray, t: np.ndarray) -> float:
    den = float((d * d).sum())
    return float(np.clip((d * t).sum() / den, 0.0, 1.0)) if den > 0 else 1.0


def fit_weights(model, predicted: np.ndarray, true: np.ndarray, groups: np.ndarray | None = None,
                landmarks: np.ndarray | None = None) -> dict:
    """Per part, the least-squares shrinkage weight in [0, 1] (module docstring) of the
    ``predicted`` (N, C M) textures towards the mean given the ``true`` ones, and the PSNR
    (dB, peak 255) over those frames of the prediction, of the mean and of the shrunk prediction.

    ``groups`` (N,) int: the held-out block of each frame; then a part's weight is the largest
    of the blocks' own least-squares weights (``fold_weights``): a part is shrunk only as far
    as every block agrees, so one block unlike the others (e.g. the only closed-mouth one)
    cannot shrink a part that the rest predict well. ``landmarks`` (N, P, 2): the frames'
    own; the mouth interior's weight then comes from the frames with an open mouth only
    (those where it is the interior, :func:`frame_regions`; a closed mouth's interior pixels
    are not counted with the lips either, whose weight those columns do not take). A block
    with no open mouth has no interior weight, and with none at all the part keeps weight 1
    (left out of the result).

    Returns {"weights": {part: w}, "psnr": {part: {"sadm", "mean_texture", "shrunk"}}[,
    "fold_weights": {part: [w per block that shows it]}]}."""
    mean = np.clip(model.appearance_pca.mean, 0, 1).astype(np.float64)
    n, c = len(true), model.n_channels
    d = (np.clip(predicted, 0, 1) - mean).reshape(n, c, -1)
    t = (np.clip(true, 0, 1) - mean).reshape(n, c, -1)
    weights, table, per_fold = {}, {}, {}

    def db(e):
        return float(10 * np.log10(1.0 / max(float((e * e).mean()), 1e-20)))

    # per part: (frames (N,), pixels (M,)) where it is weighed
    parts = {name: (np.ones(n, bool), m) for name, m in reference_regions(model).items()}
    if landmarks is not None and "mouth_interior" in parts:
        parts["mouth_interior"] = (~closed_mouths(landmarks), parts["mouth_interior"][1])
    for name, (rows, m) in parts.items():
        if not rows.any():
            continue
        dm, tm, gr = d[:, :, m], t[:, :, m], groups  # the part's columns
        if not rows.all():  # weighed on some frames only: those
            dm, tm, gr = dm[rows], tm[rows], None if groups is None else groups[rows]
        if gr is None:
            w = _ls_weight(dm, tm)
        else:
            per_fold[name] = [_ls_weight(dm[gr == g], tm[gr == g]) for g in np.unique(gr)]
            w = max(per_fold[name])
        weights[name] = w
        table[name] = {"sadm": db(dm - tm), "mean_texture": db(tm), "shrunk": db(w * dm - tm)}
    out = {"weights": weights, "psnr": table}
    if groups is not None:
        out["fold_weights"] = per_fold
    return out


def fit_region_shrink(fit, model, landmarks: np.ndarray, textures: np.ndarray, folds: int, n_val: int) -> dict:
    """Per-part shrinkage weights (:func:`fit_weights`) from held-out predictions of the
    training frames. ``fit(idx)`` fits the SADM's settings (shrinkage off) on the training
    frames ``idx`` and returns its synthesizer; ``landmarks`` (N, P, 2) and ``textures``
    (N, C M) are the N training frames'.

    ``folds`` >= 2: blocked cross-validation, the frames cut into that many contiguous blocks
    in time, each predicted by a fit on the others (every training frame is scored once);
    otherwise the last ``n_val`` frames (the validation slice), predicted by a fit on those
    before. With blocks, a part's weight is the largest of the blocks' (:func:`fit_weights`).
    The weights are then applied to the SADM fitted on all frames. Adds ``folds`` and
    ``val_frames`` (the frames scored) to the result."""
    n = len(textures)
    blocks = np.minimum(np.arange(n) * folds // n, folds - 1) if folds >= 2 else (np.arange(n) >= n - n_val).astype(int)
    scored = np.arange(n) if folds >= 2 else np.flatnonzero(blocks == 1)
    pred = np.empty((len(scored), textures.shape[1]), np.float32)
    for b in (range(folds) if folds >= 2 else (1,)):
        out = blocks == b
        syn = fit(np.flatnonzero(~out))
        with torch.no_grad():
            t = syn.texture(torch.from_numpy(np.ascontiguousarray(landmarks[out], np.float32)))
        pred[np.searchsorted(scored, np.flatnonzero(out))] = t.reshape(int(out.sum()), -1).numpy()
    result = fit_weights(model, pred, textures[scored], blocks if folds >= 2 else None, landmarks[scored])
    result.update(folds=int(folds) if folds >= 2 else 0, val_frames=int(len(scored)))
    return result


def check_shrink(value, where) -> dict | None:
    """A manifest's ``region_shrink`` (None: runs saved before it or without it), checked:
    FacesynthError naming ``where`` unless its weights map parts to numbers in [0, 1]."""
    if value is None:
        return None
    weights = value.get("weights") if isinstance(value, dict) else None
    ok = isinstance(weights, dict) and all(
        k in FACE_REGIONS and isinstance(w, (int, float)) and 0 <= w <= 1 for k, w in weights.items())
    if not ok:
        raise FacesynthError(f"{where}: region_shrink.weights must map face parts ({', '.join(FACE_REGIONS)}) "
                             "to numbers in [0, 1]")
    return dict(value)


__all__ = ["FACE_REGIONS", "reference_regions", "closed_mouths", "frame_regions", "pixel_errors", "masked_psnr01", "column_weights",
           "fit_weights", "fit_region_shrink", "check_shrink", "shrink_appearance"]
