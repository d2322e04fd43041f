"""Example-based detail from the subject's own frames (``model.detail``, 0..1).

A regressor fitted for squared error renders the conditional mean of the texture given the
landmarks: the teeth, the lips' creases and the skin's grain that the points do not fix are
averaged away. This module keeps a bank of the training frames' own detail and adds it back
where the shape says which frames look alike:

* **Bank.** At most :data:`BANK_FRAMES` evenly spaced training frames. For each, the high band
  of its reference-frame texture, ``texture - blur(texture)`` (a Gaussian of ``sigma`` =
  ``detail_sigma`` x reference width / 128 px, normalised inside the face mask so the border
  does not leak in), or its own pixels (see Blend), on the pixels of the chosen parts
  (``detail_parts``: ``interior`` = the mouth interior, ``mouth`` = mouth interior and lips,
  ``mouth+eyes``, or ``face``). Stored as int8 codes with one float scale per
  frame (the graph's compressed texture bank), beside the key of each frame: its aligned key
  points (the inner and outer lips; the inner lips alone for ``interior``; with ``eyes`` or
  ``face`` the eye contours too), in the
  face model's normalised frame (the same similarity alignment as the regressor's input).
  Since every texture lives in the reference frame, the bank is already aligned to the
  prediction point by point through the piecewise-affine warp.
* **Retrieval.** For an output frame's aligned shape q: the squared distances d to every key,
  the ``k + 1`` nearest (TopK), and inverse-distance weights ``w_i = 1/d_i - 1/d_(k+1)`` over
  the k nearest, normalised (Shepard's interpolation, cut at the (k+1)-th). A weight falls to
  zero as its frame becomes the (k+1)-th, so the blend is a continuous function of the
  landmarks (no popping when the nearest frames change), and at a training frame's own shape
  it is that frame's detail.
* **Blend.** ``texture + detail * (sum_i w_i b_i - alpha * texture)`` on the parts' pixels
  (clipped to [0, 1]), where each bank row ``b_i`` holds, per pixel, ``alpha`` times the frame's
  own pixels plus ``1 - alpha`` times its band. ``detail_band`` picks them: ``high`` (alpha 0:
  the texture minus its blur; the regressor gives the coarse band, the retrieved frames the fine
  one), ``residual`` (alpha 0: the texture minus its appearance-PCA reconstruction),
  ``texture`` (alpha 1: the frames' own pixels replace the prediction) or ``interior`` (alpha =
  the mouth interior's mask, blurred by ``detail_feather``: the whole interior, teeth and
  tongue, from the retrieved frames, faded into the high band of the lips around it, as
  Face2Face and "Synthesizing Obama" copy the mouth from the subject's own video). With
  ``detail_feather`` the parts' own edge is blurred the same way.
* **Reach.** Far from every training shape (a mouth opened wider than any in training) the
  retrieved frames are stretched over a shape they never had. ``detail_reach`` (0 = off) fades
  the detail out there: times ``1 / (1 + (d_1 / r)^2)``, with ``d_1`` the nearest key's squared
  distance and ``r`` = ``detail_reach`` times the bank's own spacing (:func:`bank_spacing`).
* **Median.** ``detail_blend=median`` replaces the weighted mean by a per-pixel weighted
  geometric median of the k colours (:func:`weighted_median`): where two neighbours show teeth
  and three a dark open mouth, the blend is a dark mouth, not a grey smear. It is computed by
  a few Weiszfeld steps from the mean, so it stays a continuous function of the weights (no
  popping) and runs in the graph as plain arithmetic.

:class:`DetailTransfer` is the torch form (TopK, Gather over the int8 bank, a batched matmul,
one Gather that spreads the parts' pixels over the texture) used by the synthesiser, the
evaluation and both exported graphs.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import nn

from facesynth.errors import FacesynthError
from facesynth.landmarks import face_region_masks, get_scheme, ibug68_view

BANK_FRAMES = 256  # training frames kept in the bank (evenly spaced)
PARTS = {"interior": ("mouth_interior",), "mouth": ("mouth_interior", "lips"),
         "mouth+eyes": ("mouth_interior", "lips", "eyes"), "face": None}
KEY_REGIONS = {"interior": ("inner_lips",), "mouth": ("outer_lips", "inner_lips"), "mouth+eyes": ("outer_lips", "inner_lips", "eyes"),
               "face": ("outer_lips", "inner_lips", "eyes", "brows")}
BANDS = ("high", "residual", "texture", "interior")
BLENDS = ("mean", "median")
MEDIAN_STEPS = 3  # Weiszfeld steps of the "median" blend (from the weighted mean)
MEDIAN_EPS = 0.02  # its smoothing: colour distance (0..1 units) below which a neighbour counts as agreeing
EPS = 1e-12  # added to the squared key distances (aligned shapes have unit norm: neighbours lie ~1e-5 apart)
BANK_TENSORS = ("detail_replace", "detail_keys", "detail_codes", "detail_scale", "detail_columns", "detail_points",
                "detail_alpha", "detail_median", "detail_reach")  # the last three absent in older banks


def check_detail(cfg) -> None:
    """FacesynthError naming the first ``model.detail*`` setting out of range."""
    if not 0 <= float(cfg.detail) <= 1:
        raise FacesynthError(f"model.detail must lie in [0, 1] (0 = off), got {cfg.detail}")
    if int(cfg.detail_k) < 1:
        raise FacesynthError(f"model.detail_k must be at least 1, got {cfg.detail_k}")
    if cfg.detail_parts not in PARTS:
        raise FacesynthError(f"model.detail_parts must be one of {sorted(PARTS)}, got {cfg.detail_parts!r}")
    if cfg.detail_band not in BANDS:
        raise FacesynthError(f"model.detail_band must be one of {BANDS}, got {cfg.detail_band!r}")
    if cfg.detail_blend not in BLENDS:
        raise FacesynthError(f"model.detail_blend must be one of {BLENDS}, got {cfg.detail_blend!r}")
    if not float(cfg.detail_feather) >= 0:
        raise FacesynthError(f"model.detail_feather must be >= 0 (px at a 128 px reference), got {cfg.detail_feather}")
    if not float(cfg.detail_reach) >= 0:
        raise FacesynthError(f"model.detail_reach must be >= 0 (0 = no gate), got {cfg.detail_reach}")
    if not float(cfg.detail_sigma) > 0:
        raise FacesynthError(f"model.detail_sigma must be positive (px at a 128 px reference), got {cfg.detail_sigma}")


def part_columns(model, parts: str, feather: float = 0.0, names: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """int64 indices of the reference-frame mask pixels (0..M-1) of ``parts`` (:data:`PARTS`;
    or the regions ``names``), cut as :func:`facesynth.landmarks.face_region_masks` cuts the
    reference shape, and their float32 weights: 1 without ``feather``; with it (px in the
    reference frame), the parts' mask blurred by a Gaussian of that sigma and divided by its
    maximum (about 0.5 on the parts' edge, fading over two sigmas either side; the pixels it
    reaches outside the parts are kept too)."""
    names = PARTS[parts] if names is None else names
    index = model.sampler().mask_index.numpy()
    if names is None:
        return np.arange(len(index), dtype=np.int64), np.ones(len(index), np.float32)
    h, w = model.reference.size
    inside = np.zeros(h * w, bool)
    inside[index] = True
    masks = face_region_masks(ibug68_view(np.asarray(model.reference.points, np.float64)), (h, w), within=inside.reshape(h, w))
    keep = np.zeros(h * w, bool)
    for n in names:
        if n in masks:
            keep |= masks[n].reshape(-1)
    if feather <= 0:
        cols = np.flatnonzero(keep[index]).astype(np.int64)
        return cols, np.ones(len(cols), np.float32)
    weight = cv2.GaussianBlur(keep.reshape(h, w).astype(np.float32), (0, 0), feather).reshape(-1)[index]
    cols = np.flatnonzero(weight >= 1 / 255).astype(np.int64)
    return cols, np.minimum(weight[cols] / weight.max(), 1).astype(np.float32)


def key_points(scheme: str, parts: str) -> np.ndarray:
    """int64 indices of the points whose aligned positions key the retrieval."""
    sch = get_scheme(scheme)
    return np.unique(np.concatenate([sch.region(r) for r in KEY_REGIONS[parts] if r in sch.regions])).astype(np.int64)


def high_band(model, textures: np.ndarray, sigma: float) -> np.ndarray:
    """(N, C * M) textures -> float32 (N, C, M): each minus its Gaussian blur (``sigma`` px,
    normalised by the blurred mask: only face pixels are averaged)."""
    index = model.sampler().mask_index.numpy()
    h, w = model.reference.size
    m = np.zeros(h * w, np.float32)
    m[index] = 1
    m = m.reshape(h, w)
    den = np.maximum(cv2.GaussianBlur(m, (0, 0), sigma), 1e-6)
    imgs = model.texture_images(textures)  # (N, H, W, C), zero outside the mask
    out = np.empty((len(textures), imgs.shape[-1], len(index)), np.float32)
    for i, img in enumerate(imgs):
        low = cv2.GaussianBlur(img, (0, 0), sigma).reshape(h, w, -1) / den[..., None]
        out[i] = (img.reshape(h, w, -1) - low).reshape(h * w, -1)[index].T
    return out


def fit_detail_bank(model, landmarks: np.ndarray, textures: np.ndarray) -> tuple[dict, dict]:
    """The bank (name -> array, :data:`BANK_TENSORS`) of a face model ``model`` from its training
    frames' (N, P, 2) ``landmarks`` and (N, C * M) ``textures``, and a report (frames, pixels,
    bytes). The bank is None when the parts hold no pixel of the reference frame (the interior
    of a reference shape whose mouth is closed)."""
    cfg = model.config
    check_detail(cfg)
    pick = np.unique(np.linspace(0, len(textures) - 1, min(BANK_FRAMES, len(textures))).round().astype(np.int64))
    px = model.reference.size[1] / 128.0  # settings in px at a 128 px reference -> this reference's px
    cols, part = part_columns(model, cfg.detail_parts, float(cfg.detail_feather) * px)
    sigma = float(cfg.detail_sigma) * px
    if len(cols) == 0:  # e.g. the interior of a reference shape whose mouth is closed: nothing to keep
        return None, {"frames": 0, "pixels": 0, "bytes": 0}
    tex = np.asarray(textures[pick], np.float32)
    own = tex.reshape(len(pick), model.n_channels, -1)[:, :, cols]  # the frames' own pixels
    if cfg.detail_band == "texture":
        alpha = np.ones(len(cols), np.float32)
    elif cfg.detail_band == "interior":  # the interior's own pixels, feathered into the high band around it
        icols, iw = part_columns(model, cfg.detail_parts, float(cfg.detail_feather) * px, names=("mouth_interior",))
        weight = np.zeros(model.n_pixels, np.float32)
        weight[icols] = iw
        alpha = weight[cols]
    else:
        alpha = np.zeros(len(cols), np.float32)
    if cfg.detail_band == "residual":  # what the appearance PCA cannot hold
        pca = model.appearance_pca
        band = (tex - pca.reconstruct(pca.project(tex))).reshape(len(pick), model.n_channels, -1)[:, :, cols]
    elif (alpha < 1).any():
        band = high_band(model, textures[pick], sigma)[:, :, cols]
    else:
        band = np.zeros_like(own)
    # per column: the frames' own pixels with weight alpha, the band with 1 - alpha, times the part's weight
    high = (part * (alpha * own + (1 - alpha) * band)).reshape(len(pick), -1)
    scale = np.maximum(np.abs(high).max(1), 1e-6).astype(np.float32) / 127.0
    codes = np.clip(np.round(high / scale[:, None]), -127, 127).astype(np.int8)
    points = key_points(model.scheme, cfg.detail_parts)
    aligned, _ = model.align(model.denoise(np.asarray(landmarks)[pick]))
    keys = aligned[:, points].reshape(len(pick), -1).astype(np.float32)
    bank = {"detail_replace": np.asarray([bool((alpha > 0).any())], np.bool_), "detail_keys": keys,
            "detail_codes": codes, "detail_scale": scale, "detail_columns": cols,
            "detail_points": points, "detail_alpha": (part * alpha).astype(np.float32),
            "detail_median": np.asarray([cfg.detail_blend == "median"], np.bool_),
            "detail_reach": np.asarray([float(cfg.detail_reach) * bank_spacing(keys)], np.float32)}
    nbytes = int(sum(v.nbytes for v in bank.values()))
    return bank, {"frames": int(len(pick)), "pixels": int(len(cols)), "sigma_px": sigma, "bytes": nbytes}


def bank_spacing(keys: np.ndarray) -> float:
    """The 90th percentile over the bank's keys of the squared distance to the nearest other
    key: how far apart neighbouring training shapes lie (the unit of ``detail_reach``)."""
    k = np.asarray(keys, np.float64)
    d = ((k[:, None] - k[None]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    return float(np.quantile(d.min(1), 0.9)) if len(k) > 1 else 0.0


def check_bank(bank: dict, n_points: int, n_channels: int, n_pixels: int) -> None:
    """ValueError naming the first bank tensor that does not fit the face model."""
    keys, codes, scale = bank["detail_keys"], bank["detail_codes"], bank["detail_scale"]
    cols, pts = bank["detail_columns"], bank["detail_points"]
    n = len(keys)
    if pts.ndim != 1 or len(pts) == 0 or pts.min() < 0 or pts.max() >= n_points or keys.shape != (n, 2 * len(pts)):
        raise ValueError(f"detail_keys/detail_points: inconsistent shapes {keys.shape}, {pts.shape}")
    if cols.ndim != 1 or len(cols) == 0 or cols.min() < 0 or cols.max() >= n_pixels:
        raise ValueError(f"detail_columns: expected indices below {n_pixels}, got shape {cols.shape}")
    if codes.dtype != np.int8 or codes.shape != (n, n_channels * len(cols)) or scale.shape != (n,):
        raise ValueError(f"detail_codes/detail_scale: expected int8 ({n}, {n_channels * len(cols)}) and ({n},)")
    alpha = bank.get("detail_alpha")
    if alpha is not None and (alpha.shape != cols.shape or not np.all((alpha >= 0) & (alpha <= 1))):
        raise ValueError(f"detail_alpha: expected {cols.shape} weights in [0, 1], got shape {alpha.shape}")
    reach = bank.get("detail_reach")
    if reach is not None and (reach.shape != (1,) or not float(reach[0]) >= 0):
        raise ValueError(f"detail_reach: expected one squared distance >= 0, got {reach}")


class DetailTransfer(nn.Module):
    """``forward(texture (B, C, M), aligned (B, P, 2))`` -> the texture with the retrieved
    frames' high band added on the bank's pixels, times ``strength`` (see the module)."""

    def __init__(self, bank: dict, k: int, strength: float, n_pixels: int):
        super().__init__()
        keys = np.asarray(bank["detail_keys"], np.float32)
        self.k = int(min(k, len(keys) - 1))
        if self.k < 1:
            raise FacesynthError("model.detail: the bank needs at least 2 frames")
        self.strength = float(strength)
        replace = bool(np.asarray(bank.get("detail_replace", False)).any())  # a texture bank: blend towards it
        self.median = bool(np.asarray(bank.get("detail_median", False)).any())  # per pixel, the neighbours' median
        self.points = [int(p) for p in bank["detail_points"]]
        cols = np.asarray(bank["detail_columns"], np.int64)
        spread = np.full(n_pixels, len(cols), np.int64)  # pixel -> its column in the bank, or the zero column
        spread[cols] = np.arange(len(cols))
        self.n_cols = len(cols)
        self.register_buffer("keys", torch.from_numpy(keys.copy()))
        self.register_buffer("codes", torch.from_numpy(np.asarray(bank["detail_codes"], np.int8).copy()))
        self.register_buffer("scale", torch.from_numpy(np.asarray(bank["detail_scale"], np.float32)[:, None].copy()))
        self.register_buffer("spread", torch.from_numpy(spread))
        self.register_buffer("cols", torch.from_numpy(cols))
        # per column, the weight of the prediction the bank's own pixels replace (older banks: all or none)
        alpha = np.asarray(bank.get("detail_alpha", np.full(len(cols), float(replace), np.float32)), np.float32)
        self.replace = bool((alpha > 0).any())
        self.register_buffer("alpha", torch.from_numpy(alpha.copy()))
        self.reach = float(np.asarray(bank.get("detail_reach", [0.0]), np.float64).reshape(-1)[0])  # 0: no gate

    def weights(self, aligned: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, k) bank rows and their (B, k) weights (rows sum to 1, or 0 when every key ties)."""
        idx, w, _ = self.retrieve(aligned)
        return idx, w

    def retrieve(self, aligned: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`weights` and the (B, 1, 1) gate ``1 / (1 + (d_1 / reach)^2)`` of the nearest
        key's squared distance ``d_1`` (1 without a reach)."""
        q = aligned[:, self.points].flatten(1)
        diff = q.unsqueeze(1) - self.keys  # (B, N, F): direct differences, no cancellation
        neg, idx = torch.topk(-(diff * diff).sum(2), self.k + 1, dim=1)
        d = -neg
        w = torch.relu(1 / (d[:, : self.k] + EPS) - 1 / (d[:, self.k :] + EPS))
        gate = 1 / (1 + (d[:, :1, None] / self.reach) ** 2) if self.reach > 0 else torch.ones_like(d[:, :1, None])
        return idx[:, : self.k], w / (w.sum(1, keepdim=True) + 1e-12), gate

    def forward(self, texture: torch.Tensor, aligned: torch.Tensor) -> torch.Tensor:
        idx, w, gate = self.retrieve(aligned)
        rows = self.codes[idx].to(torch.float32) * self.scale[idx]  # (B, k, C * Mr)
        if self.median:
            high = weighted_median(rows.reshape(rows.shape[0], self.k, texture.shape[1], self.n_cols), w)
        else:
            high = torch.matmul(w.unsqueeze(1), rows).reshape(texture.shape[0], texture.shape[1], self.n_cols)
        if self.replace:
            high = high - self.alpha * texture[:, :, self.cols]
        if self.reach > 0:
            high = high * gate
        high = torch.cat([high, torch.zeros_like(high[:, :, :1])], 2)[:, :, self.spread]
        return torch.clamp(texture + self.strength * high, 0.0, 1.0)


def weighted_median(rows: torch.Tensor, w: torch.Tensor, steps: int = MEDIAN_STEPS, eps: float = MEDIAN_EPS) -> torch.Tensor:
    """(B, k, C, M) neighbours' pixels and their (B, k) weights -> (B, C, M): per pixel, the
    weighted geometric median of the k colours, by ``steps`` Weiszfeld steps from the weighted
    mean (each neighbour re-weighted by ``w_i / sqrt(|c_i - m|^2 + eps^2)``). Unlike a sort, it
    is a continuous function of the weights and the colours (no popping as the weights move),
    a zero weight contributes nothing, and an outlier (teeth among dark mouths) is voted down."""
    w = w[:, :, None, None]
    m = (w * rows).sum(1)
    for _ in range(steps):
        u = w / torch.sqrt(((rows - m.unsqueeze(1)) ** 2).sum(2, keepdim=True) + eps * eps)
        m = (u * rows).sum(1) / (u.sum(1) + 1e-12)
    return m
