"""Zero-phase smoothing of a tracked landmark track (``data.smooth_landmarks``).

A tracker's landmarks jitter from frame to frame (dlib's are whole pixels: a still face's
points jump by about a pixel every frame), and a texture warped on them flickers. When the
whole track is known (a training video and its held-out frames), it is smoothed offline
with symmetric kernels, so nothing lags:

* each point's x and y are smoothed by two Gaussians along time, a strong one
  (:data:`SIGMA_STILL_S`) and a light one (:data:`SIGMA_MOVING_S`);
* the point's speed (the strong track's central difference, in face radii per second:
  the RMS distance of the points from their centroid) picks between them per frame,
  ``w = min(1, speed / FAST_RADII_S)``, ``out = strong + w (light - strong)``, so a still
  face gets the strong filter and a fast lip the light one;
* the light track's centroid (the mean of the points: the face's translation) stays within
  :data:`LIGHT_SHIFT_PX` of the tracked centroid, per axis: a head that jerks from one frame to
  the next (a fast shake, or a video with repeated frames whose head moves in steps) keeps
  its jerks, which the light Gaussian would round off by up to 2 px, while the centroid's
  own jitter (a few tenths of a pixel) is still smoothed;
* both kernels are symmetric and centred (zero phase): a linear ramp passes unchanged
  whatever the weights; segment ends are padded by odd reflection (as
  :func:`scipy.signal.filtfilt`'s default ``padtype='odd'``) about the end of a straight line
  fitted to the last few rows (a pivot on the end row itself would leave its jitter), which
  keeps a ramp there too.

Each segment is smoothed alone (:func:`segments`): the training and test parts of the
temporal split, and stretches of video separated by a break in the frame numbers, never see
each other's frames. Live driving (``facesynth app --smooth``) keeps the causal One Euro
filter of :mod:`facesynth.runtime.filters`: it cannot see the future.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from facesynth.data.sequence import FaceSequence
from facesynth.data.splits import temporal_split
from facesynth.errors import FacesynthError

SIGMA_STILL_S = 0.1  # Gaussian sigma (s) of a still point: 3 frames at 30 frames/s
SIGMA_MOVING_S = 0.02  # Gaussian sigma (s) of a fast point: 0.6 frames at 30 frames/s
LIGHT_SHIFT_PX = 0.3  # the most (frame px, per axis) the light filter moves the face's centroid
# (17 shared clips, docs/studies/flicker.md: keeps vrt_face4's and lp_d11's held-out PSNR within 0.07 dB of the
# tracked landmarks', and every clip's flicker <= 1.2 x the real frames' with auto + filter; None: no limit)
FAST_RADII_S = 0.25  # point speed (face radii per second) from which the light filter alone applies
# (17 shared clips with the centroid's limit, bench.studies.landmark_smoothing --fast-radii-s: 0.25 keeps every
# clip's flicker <= 1.2 x the real frames' with auto + filter too (0.2: 1.23) and no clip's PSNR more than
# 0.1 dB below the tracked landmarks' (0.35: three clips)


def _line_end(x: np.ndarray) -> np.ndarray:
    """The value at row 0 of the least-squares line through the rows of ``x`` (axis 0): the
    pivot of the odd reflection, so that the end row is smoothed too and a ramp is kept."""
    t = np.arange(len(x), dtype=np.float64) - (len(x) - 1) / 2
    mean = x.mean(axis=0)
    slope = np.tensordot(t, x - mean, axes=(0, 0)) / max(float((t ** 2).sum()), 1e-12)
    return (mean - slope * (len(x) - 1) / 2)[None]


def _gauss(x: np.ndarray, sigma: float, pad: int) -> np.ndarray:
    """Gaussian along axis 0 of float64 ``x`` with odd reflection about the ends (ramps kept)."""
    if sigma <= 0:
        return x.copy()
    pad = min(pad, len(x) - 1)
    if pad > 0:
        m = min(len(x), 4 * int(np.ceil(sigma)) + 1)
        head = 2 * _line_end(x[:m]) - x[pad:0:-1]
        tail = 2 * _line_end(x[::-1][:m]) - x[-2:-pad - 2:-1]
        xp = np.concatenate([head, x, tail])
    else:
        xp = x
    out = gaussian_filter1d(xp, sigma, axis=0, mode="nearest", truncate=4.0)
    return out[pad:pad + len(x)]


def smooth_track(landmarks: np.ndarray, rate: float, sigma_still_s: float = SIGMA_STILL_S,
                 sigma_moving_s: float = SIGMA_MOVING_S, fast_radii_s: float = FAST_RADII_S,
                 light_shift_px: float | None = LIGHT_SHIFT_PX) -> np.ndarray:
    """float32 (T, P, 2): one segment's landmarks (T, P, 2), sampled at ``rate`` rows per
    second, smoothed as the module docstring says (a segment of one or two rows is returned as is;
    ``light_shift_px`` None: the light track's centroid is not limited)."""
    lm = np.asarray(landmarks, np.float64)
    if lm.ndim != 3 or lm.shape[-1] != 2:
        raise FacesynthError(f"smooth_track: landmarks must be (T, P, 2), got {lm.shape}")
    if not np.isfinite(lm).all():
        raise FacesynthError("smooth_track: landmarks contain NaN/inf (smooth the rows with a face only)")
    if not rate > 0 or sigma_still_s < 0 or sigma_moving_s < 0 or not fast_radii_s > 0 or \
            (light_shift_px is not None and not light_shift_px > 0):
        raise FacesynthError(f"smooth_track: need rate > 0, sigmas >= 0, fast_radii_s > 0, light_shift_px > 0 or None, "
                             f"got rate={rate}, sigma_still_s={sigma_still_s}, sigma_moving_s={sigma_moving_s}, "
                             f"fast_radii_s={fast_radii_s}, light_shift_px={light_shift_px}")
    if len(lm) < 3:
        return lm.astype(np.float32)
    s_still, s_moving = sigma_still_s * rate, sigma_moving_s * rate
    pad = int(np.ceil(4 * max(s_still, s_moving))) + 1
    strong, light = _gauss(lm, s_still, pad), _gauss(lm, s_moving, pad)
    if light_shift_px is not None:  # the light track's centroid kept within light_shift_px of the tracked one
        shift = light.mean(axis=1, keepdims=True) - lm.mean(axis=1, keepdims=True)
        light += np.clip(shift, -light_shift_px, light_shift_px) - shift
    centred = lm - lm.mean(axis=1, keepdims=True)
    radius = float(np.median(np.sqrt((centred ** 2).sum(-1).mean(-1))))  # face radius (px), the segment's median
    speed = np.linalg.norm(np.gradient(strong, axis=0), axis=-1) * rate / max(radius, 1e-6)  # (T, P) radii / s
    reach = 2 * int(np.ceil(2 * s_still)) + 1  # a fast move's whole stretch, its turning points too (speed 0 there)
    w = np.minimum(1.0, maximum_filter1d(speed, reach, axis=0, mode="nearest") / fast_radii_s)[..., None]
    return (strong + w * (light - strong)).astype(np.float32)


def segments(frame_index: np.ndarray, bounds: list[int] = ()) -> list[np.ndarray]:
    """Row ranges smoothed alone: ``frame_index`` (N,) cut before each row of ``bounds`` and
    wherever the frame numbers step by more than twice their median step (a break in the video)."""
    fi = np.asarray(frame_index, np.int64)
    if len(fi) == 0:
        return []
    steps = np.diff(fi)
    step = float(np.median(steps)) if len(steps) else 1.0
    cuts = set(int(b) for b in bounds if 0 < int(b) < len(fi)) | set((np.flatnonzero(steps > 2 * step) + 1).tolist())
    edges = [0, *sorted(cuts), len(fi)]
    return [np.arange(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def split_bounds(n: int, train_fraction: float, gap: int) -> list[int]:
    """The rows where the temporal split (:func:`facesynth.data.splits.temporal_split`) cuts:
    the first gap row and the first test row."""
    tr, te = temporal_split(n, train_fraction, gap)
    return [len(tr), int(te[0])]


def smooth_sequence(seq: FaceSequence, bounds: list[int] = (), sigma_still_s: float = SIGMA_STILL_S,
                    sigma_moving_s: float = SIGMA_MOVING_S, fast_radii_s: float = FAST_RADII_S,
                    light_shift_px: float | None = LIGHT_SHIFT_PX) -> FaceSequence:
    """``seq`` with its landmarks smoothed per segment (:func:`segments` of its frame numbers
    and ``bounds``; the filter's settings as :func:`smooth_track`'s), the tracked ones kept as
    ``seq.tracked``; ``meta['landmark_smoothing']`` records the filter. The rows' rate is
    ``seq.fps`` over the median frame step."""
    fi = np.asarray(seq.frame_index)
    step = float(np.median(np.diff(fi))) if len(fi) > 1 else 1.0
    rate = float(seq.fps) / max(step, 1.0)
    out = np.empty_like(seq.landmarks)
    for rows in segments(fi, list(bounds)):
        out[rows] = smooth_track(seq.landmarks[rows], rate, sigma_still_s, sigma_moving_s, fast_radii_s, light_shift_px)
    meta = {**seq.meta, "landmark_smoothing": {
        "filter": "zero-phase motion-adaptive Gaussian (facesynth.data.smoothing)", "sigma_still_s": sigma_still_s,
        "sigma_moving_s": sigma_moving_s, "fast_radii_s": fast_radii_s, "light_shift_px": light_shift_px, "rate": rate,
        "bounds": [int(b) for b in bounds]}}
    return FaceSequence(out, seq.frame_index, seq.frames, seq.fps, seq.name, meta, seq.scheme,
                        tracked=seq.as_tracked)
