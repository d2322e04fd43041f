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
The coefficients are written to the model's metadata at export (``frame_motion``;
:mod:`facesynth.onnx.avatar`) and read back by the runtime and the talking-head graph.

The measurements behind it are in docs/reenact.md, "The avatar's video teaches the warp".
"""

from __future__ import annotations

import cv2
import numpy as np

from facesynth.errors import FacesynthError
from facesynth.runtime.fullframe import FrameWarp, motion_features

FRAMES = 60  # training frames the fit reads, evenly spaced
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
    lm = np.asarray(landmarks, np.float64)
    extra = fw.src[fw.n_face:]
    grey0 = cv2.cvtColor(fw.frame, cv2.COLOR_RGB2GRAY)
    xtx = np.zeros((len(extra), 2, 2))
    xtu = np.zeros((len(extra), 2))
    n = 0
    for frame, row in zip(frames, lm, strict=True):
        if not np.isfinite(row).all():
            continue
        frame = np.asarray(frame)
        if frame.shape != fw.frame.shape:
            raise FacesynthError(f"head motion fit: frame of shape {frame.shape}, the neutral frame's is {fw.frame.shape}")
        u = flow_at(grey0, cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), extra)  # (K', 2) observed displacements
        move, d = motion_features(fw, row)
        x = np.stack([move, np.broadcast_to(d, move.shape)], -1) * fw.free[:, :, None]  # (K', 2 axes, 2 features)
        xtx += np.einsum("kcf,kcg->kfg", x, x)
        xtu += np.einsum("kcf,kc->kf", x, u * fw.free)
        n += 1
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


__all__ = ["FRAMES", "LAMBDA", "PARALLAX_RANGE", "SHARE_RANGE", "fit_motion", "flow_at"]
