"""How the avatar's head surroundings follow its face, learned from its own video.

:class:`facesynth.runtime.fullframe.FrameWarp` moves each control point besides the
landmarks (the head's ring, the neck, the outer ring, the frame's anchors) by a share ``a``
of the head's motion ``S(p) - p`` and a share ``b`` of the parallax term ``d`` (the nose
tip's offset that ``S`` does not explain, negated):

    p' = p + a (S(p) - p) + b d

Its geometric prior (``a = w``, ``b = PARALLAX w``, with ``w`` falling off from the head's
ring) cannot know whether the hair swings, whether the background behind the head is a wall
or a flag, or how far the outline turns with the face. The training frames can: dense
optical flow from the neutral frame to each of them (OpenCV's DIS, on grey) says where each
control point went. Per point, ``(a, b)`` is fitted to those displacements by least squares
over the frames and both coordinates (on the head's ring ``a`` is then set back to 1: the
skull is rigid, and a ring that lags the face bends the head's outline; off the ring, at
most the prior's: the surroundings may follow the head less than the rule, never more, so a
camera that followed the head in the avatar's video is not replayed), shrunk towards the
prior by a ridge of ``LAMBDA`` times the mean of the point's two feature energies, and
clipped to ``SHARE_RANGE`` / ``PARALLAX_RANGE``. The ring's points above the frame read the
flow of its top row (the flow is border-replicated), like the top anchors beside them; the
still guard ring round the frame and the frame's bottom corners keep their prior (still).
The head's ring has one size in face units for every avatar by default, about right for a
mane and too wide for slick hair: its points then lie on the background beside the head
and drag it along. :func:`fit_frame_motion` fits the motion for each ring size of
``RING_SCALES`` that stays outside the face, and keeps the one whose warp best renders other
training frames (``VALIDATION`` of them, between those of the fit: PSNR of the pooled error
over the head region, warped to each frame's own landmarks; a size whose warp folds on more
of them than another's is left out). It is never wider than the default: a wider ring only
takes in more background, which the avatar's own video rewards when its camera follows the
head, and another driver then drags.

The coefficients and the ring's size are written to the model's metadata at export
(``frame_motion``; :mod:`facesynth.onnx.avatar`) and read back by the runtime and the
talking-head graph.

The measurements behind it are in docs/reenact.md, "The avatar's video teaches the warp".
"""

from __future__ import annotations

import copy

import cv2
import numpy as np

from facesynth.errors import FacesynthError
from facesynth.landmarks import ibug68_view
from facesynth.runtime.fullframe import HEAD_RING_DEG, RING_SCALE, FrameWarp, ellipse_points, face_frame, head_region, motion_features

FRAMES = 60  # training frames the fit reads, evenly spaced
VALIDATION = 20  # training frames between those that choose the ring's size
# the head ring's sizes tried (times fullframe.HEAD_AXES), and how far (face units) it must
# stay outside the neutral face's landmarks (inside, its points fold the warp across the face)
RING_SCALES = (0.7, 0.8, 0.9, 1.0)  # never wider than the default: a wider ring only takes in background
RING_CLEARANCE = 0.1  # at 0.05, a ring by the jaw folded a cheek under a strong turn (docs/reenact.md)
LAMBDA = 1.0  # the ridge towards the prior, relative to the mean feature energy of the point
SHARE_RANGE = (0.0, 1.2)
PARALLAX_RANGE = (0.0, 1.5)


def flow_at(neutral_grey: np.ndarray, grey: np.ndarray, points: np.ndarray) -> np.ndarray:
    """float64 (K, 2): how far ``points`` (K, 2) of the neutral frame moved in a frame, by DIS
    optical flow (medium preset) from the neutral to the frame, both uint8 (H, W) grey, read
    bilinearly (the border's flow beyond it)."""
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(neutral_grey, grey, None)
    x = points[:, 0].astype(np.float32)[None]
    y = points[:, 1].astype(np.float32)[None]
    return cv2.remap(flow, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0].astype(np.float64)


def fit_motion(fw: FrameWarp, frames, landmarks: np.ndarray, lam: float = LAMBDA) -> tuple[np.ndarray, dict]:
    """Per-point motion coefficients (K - 68, 2) ``(a, b)`` for ``fw`` (the avatar's neutral
    frame and landmarks) from its training ``frames`` (iterable of uint8 (H, W, 3) RGB) and
    their ``landmarks`` (N, P, 2), and a summary {"frames", "lambda", "points_fitted"}."""
    return fit_motions([fw], frames, landmarks, lam)[0]


def fit_motions(warps: list[FrameWarp], frames, landmarks: np.ndarray, lam: float = LAMBDA) -> list[tuple[np.ndarray, dict]]:
    """:func:`fit_motion` of several warps of one neutral frame (their rings of different
    sizes), the frames read and their flow computed once."""
    lm = np.asarray(landmarks, np.float64)
    frame0 = warps[0].frame
    extras = [fw.src[fw.n_face:] for fw in warps]
    splits = np.cumsum([len(e) for e in extras])[:-1]
    grey0 = cv2.cvtColor(frame0, cv2.COLOR_RGB2GRAY)
    xtx = [np.zeros((len(e), 2, 2)) for e in extras]
    xtu = [np.zeros((len(e), 2)) for e in extras]
    n = 0
    for frame, row in zip(frames, lm, strict=True):
        if not np.isfinite(row).all():
            continue
        frame = np.asarray(frame)
        if frame.shape != frame0.shape:
            raise FacesynthError(f"head motion fit: frame of shape {frame.shape}, the neutral frame's is {frame0.shape}")
        flow = np.split(flow_at(grey0, cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), np.concatenate(extras)), splits)
        for k, (fw, u) in enumerate(zip(warps, flow, strict=True)):  # u (K', 2): the observed displacements
            move, d = motion_features(fw, row)
            x = np.stack([move, np.broadcast_to(d, move.shape)], -1) * fw.free[:, :, None]  # (K', 2 axes, 2 features)
            xtx[k] += np.einsum("kcf,kcg->kfg", x, x)
            xtu[k] += np.einsum("kcf,kc->kf", x, u * fw.free)
        n += 1
    return [_solve(fw, a, b, n, lam) for fw, a, b in zip(warps, xtx, xtu, strict=True)]


def _solve(fw: FrameWarp, xtx: np.ndarray, xtu: np.ndarray, n: int, lam: float) -> tuple[np.ndarray, dict]:
    """The ridge least squares of :func:`fit_motion` from its normal equations (K', 2, 2), (K', 2)."""
    prior = fw.prior()
    coef = prior.copy()
    fitted = ~fw.guard & fw.free.any(1)  # the guard ring and the bottom corners stay still
    if n:
        mu = lam * 0.5 * np.trace(xtx, axis1=1, axis2=2)[:, None, None] * np.eye(2)  # (K', 2, 2)
        fit = np.linalg.solve(xtx + mu + 1e-9 * np.eye(2), (xtu + np.einsum("kfg,kg->kf", mu, prior))[..., None])[..., 0]
        # the head's ring moves with the face in full (a rigid skull): its fitted a is dropped,
        # not fixed before the fit, where it takes up the flow's shortfall on large motions
        # (DIS reads ~5 % short), which would otherwise bias b
        ring = fw.on_ring
        fit[ring, 0] = prior[ring, 0]
        # off the ring, the surroundings may follow the head less than the prior, never more:
        # a camera that followed the head in the avatar's video is not replayed on another's
        fit[~ring] = np.minimum(fit[~ring], prior[~ring])
        coef[fitted] = fit[fitted]
    coef[:, 0] = np.clip(coef[:, 0], *SHARE_RANGE)
    coef[:, 1] = np.clip(coef[:, 1], *PARALLAX_RANGE)
    return coef, {"frames": n, "lambda": float(lam), "points_fitted": int(fitted.sum()) if n else 0}


def _with_motion(fw: FrameWarp, coef: np.ndarray) -> FrameWarp:
    """``fw`` with the fitted ``coef`` (K - 68, 2) as its motion: a copy sharing its control
    points, triangulation and grid, which do not depend on the motion."""
    out = copy.copy(fw)
    out.motion = coef
    return out


def ring_clearance(neutral: np.ndarray, ring_scale: float) -> float:
    """How far (face units: outer-eye-corner distances) the head's ring at ``ring_scale``
    stays outside the hull of the (P, 2) neutral face's landmarks; negative when a ring point
    lies inside the face."""
    face = ibug68_view(neutral)
    o, axes, unit = face_frame(face)
    hull = cv2.convexHull(((face - o) @ axes.T / unit).astype(np.float32))
    ring = ellipse_points(HEAD_RING_DEG, ring_scale)
    return -max(cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in ring)


def fit_frame_motion(frame: np.ndarray, neutral: np.ndarray, fit_frames, fit_landmarks: np.ndarray, val_frames,
                     val_landmarks: np.ndarray, scales=RING_SCALES) -> tuple[FrameWarp, dict]:
    """The avatar's warp: for each ring size of ``scales`` whose ring clears the neutral face
    by ``RING_CLEARANCE`` (:func:`ring_clearance`; the largest size when none does), the
    motion fitted on ``fit_frames``
    (:func:`fit_motions`); then the size whose warp best renders the validation frames
    (other training frames, ``val_frames`` with their ``val_landmarks``: PSNR of the error
    pooled over :func:`head_region`, the warp driven by each frame's own landmarks), any that
    folds the frame (:meth:`FrameWarp.folds` outside the face) on more of them than another
    left out. ``frame`` uint8 (H, W, 3) and ``neutral`` (P, 2): the avatar's neutral. Returns
    the warp and the summary of :func:`fit_motion` with ``ring_scale``, ``validation_frames``
    and ``ring_scores`` ({scale: dB}, None where the ring enters the face or the warp folds
    more; without validation frames all None and the size nearest ``RING_SCALE``)."""
    allowed = [float(s) for s in scales if ring_clearance(neutral, s) >= RING_CLEARANCE] or [float(max(scales))]
    priors = [FrameWarp(frame, neutral, ring_scale=s) for s in allowed]
    fits = fit_motions(priors, fit_frames, fit_landmarks)
    warps = [_with_motion(fw, coef) for fw, (coef, _) in zip(priors, fits, strict=True)]
    sse, folded, pixels, n = np.zeros(len(warps)), np.zeros(len(warps), int), 0, 0
    for real, lm in zip(val_frames, np.asarray(val_landmarks, np.float64), strict=True):
        if not np.isfinite(lm).all():
            continue
        real = np.asarray(real)
        mask = head_region(ibug68_view(lm), real.shape[1::-1])
        for k, fw in enumerate(warps):
            sse[k] += float(((fw(lm)[mask].astype(np.float64) - real[mask]) ** 2).sum())
            folded[k] += fw.folds(lm, outside_face=True) > 0
        pixels += int(mask.sum()) * real.shape[2]
        n += 1
    # PSNR of the pooled error (a frame the warp renders exactly, the neutral's, weighs as any);
    # a size that folds more of the frames than another does is left out
    ok = folded == folded.min()
    db = 10.0 * np.log10(255.0 ** 2 * max(pixels, 1) / np.maximum(sse, 1e-12))
    scores = {s: round(float(v), 3) if (good and n) else None for s, v, good in zip(allowed, db, ok, strict=True)}
    best = int(np.argmax(np.where(ok, db, -np.inf))) if n else int(np.argmin(np.abs(np.asarray(allowed) - RING_SCALE)))
    info = {**fits[best][1], "ring_scale": allowed[best], "validation_frames": n,
            "ring_scores": {f"{s:g}": scores.get(float(s)) for s in scales}}
    return warps[best], info


__all__ = ["FRAMES", "LAMBDA", "PARALLAX_RANGE", "RING_CLEARANCE", "RING_SCALES", "SHARE_RANGE", "VALIDATION",
           "fit_frame_motion", "fit_motion", "fit_motions", "flow_at", "ring_clearance"]
