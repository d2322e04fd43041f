"""Geometry of the embedded synthetic subject: mean face, expression controls, head motion.

Everything here is **synthetic**: a hand-made 68-point face in iBUG 300-W order and
hand-made linear expression displacement fields, in the spirit of a point distribution
model (Cootes et al., "Active Shape Models", CVIU 1995): a frame's shape is

    s = T_pose( mean + sum_k c_k D_k )

with expression controls ``c`` (``CONTROL_NAMES``) and a small similarity transform
``T_pose`` (head motion). The rigid points (eye corners, nose bridge and tip) are not
moved by any control, so a similarity fitted on them recovers ``T_pose`` exactly and
:func:`estimate_controls` recovers ``c`` from landmarks alone -- the renderer uses that
to make appearance a function of shape.

Shape units ("face units"): x to the right, y down, jaw width about 0.9.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from facesynth.geometry import apply_affine, invert_affine, similarity_fit
from facesynth.landmarks import RIGID_INNER

CONTROL_NAMES = ("jaw_open", "smile", "brow_raise", "eye_close")

# Mean 68-point face in [0, 1]-ish face units, iBUG order. Hand-adjusted from the commonly
# used dlib mean-face template (as in OpenFace's alignment); symmetrised below.
_TEMPLATE = np.array([
    (0.079, 0.339), (0.083, 0.457), (0.097, 0.576), (0.122, 0.692), (0.169, 0.800), (0.240, 0.896),
    (0.326, 0.977), (0.422, 1.043), (0.532, 1.061), (0.641, 1.040), (0.738, 0.972), (0.824, 0.890),
    (0.895, 0.792), (0.939, 0.682), (0.961, 0.562), (0.971, 0.442), (0.971, 0.322),
    (0.164, 0.249), (0.218, 0.204), (0.291, 0.192), (0.367, 0.204), (0.439, 0.233),
    (0.586, 0.228), (0.660, 0.196), (0.737, 0.182), (0.813, 0.193), (0.871, 0.235),
    (0.515, 0.319), (0.516, 0.396), (0.517, 0.474), (0.518, 0.553),
    (0.434, 0.604), (0.476, 0.621), (0.521, 0.634), (0.566, 0.619), (0.607, 0.602),
    (0.252, 0.331), (0.299, 0.303), (0.356, 0.303), (0.404, 0.339), (0.353, 0.350), (0.297, 0.350),
    (0.631, 0.334), (0.679, 0.296), (0.736, 0.295), (0.783, 0.321), (0.740, 0.342), (0.685, 0.344),
    (0.353, 0.746), (0.415, 0.719), (0.478, 0.707), (0.523, 0.717), (0.570, 0.705), (0.635, 0.716),
    (0.700, 0.739), (0.639, 0.805), (0.576, 0.835), (0.525, 0.842), (0.476, 0.838), (0.414, 0.810),
    (0.380, 0.750), (0.478, 0.745), (0.523, 0.749), (0.571, 0.743),
    (0.672, 0.744), (0.573, 0.777), (0.523, 0.780), (0.477, 0.779),
], dtype=np.float64)

# Left-right mirror permutation of the iBUG 68 markup.
MIRROR = np.array(
    list(range(16, -1, -1)) + list(range(26, 16, -1)) + [27, 28, 29, 30] + [35, 34, 33, 32, 31]
    + [45, 44, 43, 42, 47, 46] + [39, 38, 37, 36, 41, 40]
    + [54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55] + [64, 63, 62, 61, 60, 67, 66, 65]
)
# Points no control moves: eye corners, nose bridge, nose tip and wings.
RIGID = np.array(RIGID_INNER)


def _mean_shape() -> np.ndarray:
    p = _TEMPLATE.copy()
    cx = p[:, 0].mean()
    mirrored = np.stack([2 * cx - p[MIRROR, 0], p[MIRROR, 1]], axis=1)
    p = 0.5 * (p + mirrored)
    # Neutral mouth closed: inner upper and lower lips meet.
    for up, lo in ((61, 67), (62, 66), (63, 65)):
        y = 0.5 * (p[up, 1] + p[lo, 1])
        p[up, 1] = p[lo, 1] = y
    p[[60, 64], 1] = p[[61, 63], 1] + 0.002
    return p - np.array([cx, 0.0])  # x centred on 0


MEAN_SHAPE = _mean_shape()  # (68, 2) face units, x centred


def _displacements() -> np.ndarray:
    """Expression displacement fields D (K, 68, 2), face units, for controls at 1."""
    m = MEAN_SHAPE
    d = np.zeros((len(CONTROL_NAMES), 68, 2))
    # jaw_open: the jaw rotates down; lower lip and chin follow, upper lip barely moves.
    jaw = d[0]
    chin_y = m[8, 1]
    for i in range(3, 14):
        jaw[i, 1] = 0.17 * np.clip((m[i, 1] - 0.62) / (chin_y - 0.62), 0, 1) ** 1.2
    jaw[[55, 56, 57, 58, 59], 1] = [0.10, 0.135, 0.145, 0.135, 0.10]
    jaw[[65, 66, 67], 1] = [0.125, 0.135, 0.125]
    jaw[[48, 54], 1] = 0.055
    jaw[[60, 64], 1] = 0.06
    jaw[[48, 54], 0] = [0.012, -0.012]  # corners come in a little
    jaw[[49, 50, 51, 52, 53], 1] = -0.008
    jaw[[61, 62, 63], 1] = -0.004
    # smile: corners out and up, upper lip up, cheeks widen, lower lids pushed up.
    sm = d[1]
    sm[[48, 54], 0] = [-0.065, 0.065]
    sm[[48, 54], 1] = -0.055
    sm[[60, 64], 0] = [-0.055, 0.055]
    sm[[60, 64], 1] = -0.045
    sm[[49, 53], 0] = [-0.03, 0.03]
    sm[[49, 53], 1] = -0.03
    sm[[59, 55], 0] = [-0.035, 0.035]
    sm[[59, 55], 1] = -0.03
    sm[[58, 56], 0] = [-0.015, 0.015]
    sm[[58, 56], 1] = -0.01
    sm[[50, 51, 52], 1] = -0.015
    sm[[61, 62, 63], 1] = -0.012
    sm[[67, 66, 65], 1] = -0.012
    sm[[61, 63, 67, 65], 0] = [-0.02, 0.02, -0.02, 0.02]
    sm[[2, 3, 4], 0] = [-0.01, -0.015, -0.01]
    sm[[14, 13, 12], 0] = [0.01, 0.015, 0.01]
    sm[[40, 41, 46, 47], 1] = -0.012
    # brow_raise: brows up (inner a bit more), upper lids slightly up.
    br = d[2]
    br[17:27, 1] = -np.array([0.05, 0.06, 0.065, 0.068, 0.07, 0.07, 0.068, 0.065, 0.06, 0.05])
    br[[37, 38, 43, 44], 1] = -0.008
    # eye_close: upper lid points move onto the lower lid (slightly above it).
    ec = d[3]
    for up, lo in ((37, 41), (38, 40), (43, 47), (44, 46)):
        ec[up] = 0.92 * (m[lo] - m[up])
        ec[lo, 1] = -0.004
    assert not d[:, RIGID].any()
    return d


DISPLACEMENTS = _displacements()  # (K, 68, 2)


def smooth_controls(n_frames: int, rng: np.random.Generator, fps: float = 30.0) -> np.ndarray:
    """Random smooth expression controls in [0, 1], float64 (n_frames, K).

    Each control is Gaussian-filtered white noise (time scale ~0.3-0.7 s), standardised
    by its theoretical deviation (so short sequences behave like long ones) and passed
    through a smoothstep above a threshold: the face rests near neutral part of the time
    and makes expressions of varying strength otherwise. ``eye_close`` uses a short time
    scale and a high threshold, giving blink-like events.
    """
    #            sigma (s), low, high  (in standard deviations)
    spec = {"jaw_open": (0.5, -0.2, 1.4), "smile": (0.7, -0.3, 1.3),
            "brow_raise": (0.6, -0.1, 1.5), "eye_close": (0.12, 0.9, 1.9)}
    out = np.zeros((n_frames, len(CONTROL_NAMES)))
    for k, name in enumerate(CONTROL_NAMES):
        sigma_s, lo, hi = spec[name]
        sigma = max(sigma_s * fps, 1.0)
        pad = int(4 * sigma) + 1
        x = gaussian_filter1d(rng.standard_normal(n_frames + 2 * pad), sigma)[pad : pad + n_frames]
        x /= 1.0 / np.sqrt(2.0 * np.sqrt(np.pi) * sigma)
        t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
        out[:, k] = t * t * (3 - 2 * t)
    return out


def smooth_head_motion(n_frames: int, rng: np.random.Generator, fps: float = 30.0,
                       shift: float = 0.025, angle_deg: float = 3.0, scale: float = 0.03) -> np.ndarray:
    """Slight head motion, float64 (n_frames, 4): (dx, dy) as a fraction of the image
    size, roll angle in degrees, log scale. Smooth (1 s time scale) and small."""
    sigma = max(1.0 * fps, 1.0)
    pad = int(4 * sigma) + 1
    x = gaussian_filter1d(rng.standard_normal((n_frames + 2 * pad, 4)), sigma, axis=0)[pad : pad + n_frames]
    x /= 1.0 / np.sqrt(2.0 * np.sqrt(np.pi) * sigma)
    return np.clip(x, -2.5, 2.5) / 2.5 * np.array([shift, shift, angle_deg, scale])


def pose_matrices(pose: np.ndarray, size: int) -> np.ndarray:
    """Similarity matrices (T, 2, 3) mapping face units to image pixels.

    The neutral face is centred at 0.5 W horizontally and spans about half the image width.
    """
    pose = np.atleast_2d(pose)
    s = 0.56 * size * np.exp(pose[:, 3])
    a = np.deg2rad(pose[:, 2])
    c, sn = s * np.cos(a), s * np.sin(a)
    # face-unit anchor (0, 0.62) goes to (0.5, 0.56) * size + shift
    ax, ay = 0.0, 0.62
    tx = (0.5 + pose[:, 0]) * size - (c * ax - sn * ay)
    ty = (0.56 + pose[:, 1]) * size - (sn * ax + c * ay)
    return np.stack([np.stack([c, -sn, tx], 1), np.stack([sn, c, ty], 1)], 1)


def shapes_from_controls(controls: np.ndarray) -> np.ndarray:
    """Face-unit shapes (T, 68, 2) = mean + controls @ displacements."""
    return MEAN_SHAPE[None] + np.einsum("tk,kpd->tpd", np.atleast_2d(controls), DISPLACEMENTS)


def estimate_pose_and_controls(landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Recover, from image landmarks (T, 68, 2), the face-unit -> image similarity (T, 2, 3)
    (least squares on the rigid points) and the controls (T, K) (least squares on the
    residual displacement). Exact for shapes produced by this module."""
    lm = np.asarray(landmarks, dtype=np.float64).reshape(-1, 68, 2)
    m = similarity_fit(MEAN_SHAPE[RIGID][None], lm[:, RIGID])
    inv = invert_affine(m)
    local = apply_affine(lm, inv) - MEAN_SHAPE[None]
    basis = DISPLACEMENTS.reshape(len(CONTROL_NAMES), -1).T  # (136, K)
    controls = np.linalg.lstsq(basis, local.reshape(len(lm), -1).T, rcond=None)[0].T
    return m, controls
