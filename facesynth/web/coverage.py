"""The studio's coverage meter (Python reference of ``page/coverage.js``, step for step): how much
of the expression space an avatar will be driven through a recording covers.

Each frame's 478 tracker points (MediaPipe, the scheme ``mediapipe478``) are read on their iBUG-68
view (the scheme's table, as the face model sees a 478-point clip) plus the two iris centres.
Ten features are ratios of distances, so a frame's position, size and in-plane rotation (what
the face model's Procrustes alignment removes) do not change them (``iod``: the outer eye
corners 36-45; ``u`` the unit vector 36 -> 45, ``v`` its perpendicular, down the face; ``eyes``
the mean of points 36-47):

==============  =====================================================================
mouth_open      mean inner-lip gap (61-67, 62-66, 63-65) / iod
mouth_width     mouth corners 48-54 / iod
brow_height     mean over the brows 17-26 of (eyes - brow) . v / iod
brow_gap        inner brow ends 21-22 / iod
eye_open        mean eyelid gap (37-41, 38-40, 43-47, 44-46) / iod
gaze_x, gaze_y  (mean iris centre 468, 473 - eyes) . u (. v) / iod
yaw             (nose tip 30 - middle of 0 and 16) . u / |16 - 0|
==============  =====================================================================

A *direction* is a feature, a sign and a target change from the recording's neutral (the
per-feature median over the neutral prompt's frames; over every frame when that prompt has none):
``DIRECTIONS``. Its coverage on some frames is ``clip(mean of the 3 largest signed changes /
target, 0, 1)`` (the mean of the top 3 rather than the maximum: one mistracked frame does not
fill a direction). A prompt's coverage is the mean of its directions' coverage on its own frames
(the neutral prompt: the share of its frames with a face); the recording's is the mean of every
direction's coverage on all its frames. The targets are set by hand (a wide-open mouth opens by
about a third of the eye-corner distance). Across the shared clips the measure ranks clips
opposite to their held-out PSNR (lively clips are both well covered and hard to render:
``bench/studies/coverage_heldout.py``, docs/studio.md): it says what a recording lacks, not how well its
avatar will score.
"""

from __future__ import annotations

import numpy as np

from facesynth.landmarks import get_scheme

FEATURES = ("mouth_open", "mouth_width", "brow_height", "brow_gap", "eye_open", "gaze_x", "gaze_y", "yaw")
# name -> (feature, sign, target change from the neutral)
DIRECTIONS: dict[str, tuple[str, int, float]] = {
    "speech": ("mouth_open", 1, 0.12),
    "smile": ("mouth_width", 1, 0.12),
    "mouth_open": ("mouth_open", 1, 0.30),
    "oo": ("mouth_width", -1, 0.10),
    "brows_up": ("brow_height", 1, 0.05),
    "frown": ("brow_gap", -1, 0.04),
    "blink": ("eye_open", -1, 0.07),
    "gaze_left": ("gaze_x", 1, 0.03),
    "gaze_right": ("gaze_x", -1, 0.03),
    "gaze_up": ("gaze_y", -1, 0.02),
    "gaze_down": ("gaze_y", 1, 0.02),
    "turn_left": ("yaw", 1, 0.08),
    "turn_right": ("yaw", -1, 0.08),
}
TOP = 3  # a direction's reach: the mean of its TOP largest changes
IRIS_CENTRES = (468, 473)


def features(points: np.ndarray) -> np.ndarray:
    """(T, 478, 2) tracker points -> float64 (T, len(FEATURES)), in the order of :data:`FEATURES`."""
    p = np.asarray(points, np.float64)
    s = np.einsum("kp,tpc->tkc", get_scheme("mediapipe478").ibug68_matrix(), p)
    iod = np.linalg.norm(s[:, 45] - s[:, 36], axis=-1)
    u = (s[:, 45] - s[:, 36]) / iod[:, None]
    v = np.stack([-u[:, 1], u[:, 0]], -1)
    eyes = s[:, 36:48].mean(1)
    gap = lambda a, b: np.linalg.norm(s[:, a] - s[:, b], axis=-1)  # noqa: E731
    dot = lambda a, b: (a * b).sum(-1)  # noqa: E731
    iris = p[:, list(IRIS_CENTRES)].mean(1)
    width = np.linalg.norm(s[:, 16] - s[:, 0], axis=-1)
    out = [
        (gap(61, 67) + gap(62, 66) + gap(63, 65)) / 3 / iod,
        gap(48, 54) / iod,
        dot(eyes[:, None] - s[:, 17:27], v[:, None]).mean(1) / iod,
        gap(21, 22) / iod,
        (gap(37, 41) + gap(38, 40) + gap(43, 47) + gap(44, 46)) / 4 / iod,
        dot(iris - eyes, u) / iod,
        dot(iris - eyes, v) / iod,
        dot(s[:, 30] - (s[:, 0] + s[:, 16]) / 2, u) / width,
    ]
    return np.stack(out, -1)


def direction_coverage(feats: np.ndarray, neutral: np.ndarray, direction: str) -> float:
    """Coverage in [0, 1] of ``direction`` by frames ``feats`` (T, F) against ``neutral`` (F,)."""
    name, sign, target = DIRECTIONS[direction]
    k = FEATURES.index(name)
    if len(feats) == 0:
        return 0.0
    change = np.sort(sign * (feats[:, k] - neutral[k]))[::-1][:TOP]
    return float(np.clip(change.mean() / target, 0.0, 1.0))


def coverage(prompts: list[dict]) -> dict:
    """``prompts``: ``[{"id", "directions": [...], "points": [(478, 2) array or None per frame]}]``
    (the first prompt with no directions is the neutral) -> ``{"prompts": {id: coverage},
    "directions": {name: coverage on every frame}, "overall": mean of the directions}``."""
    per = []
    for p in prompts:
        pts = [np.asarray(x, np.float64).reshape(-1, 2) for x in p["points"] if x is not None]
        per.append((p, features(np.stack(pts)) if pts else np.zeros((0, len(FEATURES)))))
    every = np.concatenate([f for _, f in per]) if per else np.zeros((0, len(FEATURES)))
    neutral_feats = next((f for p, f in per if not p["directions"] and len(f)), every)
    if len(neutral_feats) == 0:
        return {"prompts": {p["id"]: 0.0 for p in prompts}, "directions": {d: 0.0 for d in DIRECTIONS}, "overall": 0.0}
    neutral = np.median(neutral_feats, axis=0)
    out = {}
    for p, f in per:
        if p["directions"]:
            out[p["id"]] = float(np.mean([direction_coverage(f, neutral, d) for d in p["directions"]]))
        else:
            out[p["id"]] = len(f) / max(1, len(p["points"]))
    dirs = {d: direction_coverage(every, neutral, d) for d in DIRECTIONS}
    return {"prompts": out, "directions": dirs, "overall": float(np.mean(list(dirs.values())))}
