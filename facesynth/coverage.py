"""The studio's coverage meter (Python reference of ``page/coverage.js``, step for step): how much
of the expression space an avatar will be driven through a recording covers.

Each frame's 478 tracker points (MediaPipe, the scheme ``mediapipe478``) are read on their iBUG-68
view (the scheme's table, as the face model sees a 478-point clip) plus the two iris centres.
Eight features are ratios of distances, so a frame's position, size and in-plane rotation (what
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

The meter measures how well the recorded frames cover the expressions the avatar will be asked
to render, in this feature space: a frame is the vector ``z = (features - neutral) / SCALE``
(the neutral: the per-feature median over the neutral prompt's frames, over every frame when
that prompt has none; ``SCALE``: each feature's typical change in an expression), and a shape
to render is *reached* by frames ``Z`` by ``clip(1 - d / REACH, 0, 1)``, ``d`` the mean distance
to its ``NEAREST`` nearest frames (three rather than one: a single mistracked frame does not
reach a shape). The shapes to render are unknown while recording, so the page uses a fixed
prior, :data:`DIRECTIONS`: a feature, a sign and a target change from the neutral (a wide-open
mouth opens by about a third of the eye-corner distance), i.e. ``z = sign * target / SCALE`` on
that feature, the others free (a smile may open the mouth too: the distance is over that
feature alone). A prompt's coverage is its directions'
mean reach by its own frames (the neutral prompt: the share of its frames with a face); the
recording's is every direction's mean reach by all its frames; the prompts whose coverage is
below :data:`WEAK` are the ones the page lists as missing or weak.

The page's headline figure is another reading of the same reach (:func:`self_reach`): the
recording cut into blocks of one second (:data:`BLOCK` frames at the page's :data:`KEEP_FPS`),
each frame's reach by the frames of the other blocks, the mean over the frames. It asks of the
recording what held-out frames ask of a training clip: are its unseen moments near the ones it
has? On the 17 shared clips the reach tells which held-out frames fail: within a clip, the
frames the recording reaches less render worse (15 clips of 17), while across clips the
headline ranks held-out quality only weakly, no better than how little the recording moves
(``bench/studies/coverage_heldout.py``, docs/studies/coverage-meter.md). With a clip's
held-out frames as the shapes to render (:func:`heldout_coverage`, known only after the fact)
the reach predicts best.

The avatar knows those shapes while it is driven: its file carries its training frames as the
meter reads them (the metadata entry :data:`RECORDING_KEY`, :func:`recording_entry`, written at
export; z from the avatar's own neutral, the one the retargeting uses), and the live page and
the studio show each driver frame's reach by them (:func:`driver_reach`, the driver's z from the
driver's neutral).
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme

FEATURES = ("mouth_open", "mouth_width", "brow_height", "brow_gap", "eye_open", "gaze_x", "gaze_y", "yaw")
# each feature's typical change in an expression (the unit of its axis)
SCALE = (0.12, 0.10, 0.05, 0.04, 0.07, 0.03, 0.02, 0.08)
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
NEAREST = 3  # a shape's distance: the mean over its NEAREST nearest frames
REACH = 1.0  # distance (in SCALE units) at which a shape counts as not reached at all
# the same for a driver's frame (driver_reach): read from the driver's own neutral, a whole frame lies
# farther from the recording's than a prompt's one feature does (the page's neutral sits a median 1.4
# units from the avatar's on the shared clips), and at 1.0 the readout sat at 0 on most frames;
# doubled, it ranks the clips' held-out PSNR as well (docs/studio.md)
DRIVE_REACH = 2.0
WEAK = 0.5  # a prompt below this coverage is listed as missing or weak
KEEP_FPS = 15  # frames a second the page keeps while recording (studio.js's KEEP_FPS)
BLOCK = KEEP_FPS  # self_reach's blocks: one second of the recording
IRIS_CENTRES = (468, 473)
RECORDING_KEY = "coverage_recording"  # the avatar's metadata entry (facesynth.contract)
MAX_RECORDED = 1000  # rows of that entry at most (evenly spaced): ~70 kB of JSON
DECIMALS = 4  # its z, rounded (1e-4 of a feature's unit)
N_POINTS = 478


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


def distance(frames_z: np.ndarray, shapes_z: np.ndarray) -> np.ndarray:
    """Each shape of ``shapes_z`` (S, F)'s mean distance to its NEAREST nearest frames of
    ``frames_z`` (T >= 1, F): (S,), in SCALE units. A shape's NaN features are free: the
    distance is over the others."""
    shapes_z = np.atleast_2d(shapes_z)
    diff = shapes_z[:, None, :] - frames_z[None]
    d = np.sqrt(np.where(np.isnan(diff), 0.0, diff ** 2).sum(-1))
    return np.sort(d, axis=1)[:, :NEAREST].mean(1)


def reach(frames_z: np.ndarray, shapes_z: np.ndarray, scale: float = REACH) -> np.ndarray:
    """How well frames ``frames_z`` (T, F) reach each shape of ``shapes_z`` (S, F), both in SCALE
    units from the neutral: (S,) in [0, 1], ``1 - distance / scale`` clipped (0 for every shape
    when there is no frame); ``scale``: :data:`REACH`, or :data:`DRIVE_REACH` for a driver's frames."""
    shapes_z = np.atleast_2d(shapes_z)
    if len(frames_z) == 0:
        return np.zeros(len(shapes_z))
    return np.clip(1.0 - distance(frames_z, shapes_z) / scale, 0.0, 1.0)


def to_z(feats: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    return (feats - neutral) / np.asarray(SCALE)


def direction_z(direction: str) -> np.ndarray:
    """A direction's target shape, in SCALE units from the neutral: its feature's target change,
    the other features free (NaN: a smile may open the mouth too)."""
    name, sign, target = DIRECTIONS[direction]
    k = FEATURES.index(name)
    z = np.full(len(FEATURES), np.nan)
    z[k] = sign * target / SCALE[k]
    return z


def direction_coverage(feats: np.ndarray, neutral: np.ndarray, direction: str) -> float:
    """Coverage in [0, 1] of ``direction`` by frames ``feats`` (T, F) against ``neutral`` (F,)."""
    return float(reach(to_z(feats, neutral), direction_z(direction))[0])


def self_reach(feats: np.ndarray, block: int = BLOCK) -> float:
    """The recording's reach of itself, cross-validated in time: ``feats`` (T, F) in recording
    order, cut into consecutive blocks of ``block`` frames; each frame's reach by the frames of
    the other blocks; the mean over the T frames (0 when there is no frame). The neutral
    cancels (only distances between frames count)."""
    z = np.asarray(feats, np.float64) / np.asarray(SCALE)
    if len(z) == 0:
        return 0.0
    per = [reach(np.concatenate([z[:s], z[s + block:]]), z[s:s + block]) for s in range(0, len(z), block)]
    return float(np.concatenate(per).mean())


def kept(times: np.ndarray, keep_fps: float = KEEP_FPS) -> np.ndarray:
    """Indices of the frames the page keeps of frames taken at ``times`` (seconds): in time order,
    a frame when at least ``1 / keep_fps`` - 2 ms passed since the last kept one (studio.js's
    rule); returned in increasing index order."""
    times = np.asarray(times, np.float64)
    out, last = [], -np.inf
    for i in np.argsort(times, kind="stable"):
        if times[i] - last >= 1 / keep_fps - 0.002:
            out.append(i)
            last = times[i]
    return np.sort(np.asarray(out, np.int64))


def recording_entry(landmarks: np.ndarray, neutral: np.ndarray, times: np.ndarray | None = None) -> dict | None:
    """The avatar's :data:`RECORDING_KEY` metadata entry: its training frames ``landmarks``
    (N, 478, 2) as the meter reads them, kept as the page keeps frames (:func:`kept`, at
    :data:`KEEP_FPS`) when their ``times`` (N,) in seconds are known (else every frame), those
    whose features are not finite dropped, at most :data:`MAX_RECORDED` of them (evenly spaced);
    ``{"features": FEATURES, "scale": SCALE, "neutral": the features of ``neutral`` (478, 2),
    "keep_fps": KEEP_FPS or None, "z": (T, F) their z from that neutral, rounded}``. None when no
    frame is left or the neutral's features are not finite."""
    lm = np.asarray(landmarks, np.float64)
    if times is not None:
        lm = lm[kept(times)]
    with np.errstate(invalid="ignore", divide="ignore"):  # a degenerate face: not finite, dropped
        ref = features(np.asarray(neutral, np.float64)[None])[0]
        z = to_z(features(lm), ref) if len(lm) else np.zeros((0, len(FEATURES)))
    if not np.isfinite(ref).all():
        return None
    z = z[np.isfinite(z).all(1)]
    if not len(z):
        return None
    z = z[np.unique(np.linspace(0, len(z) - 1, min(MAX_RECORDED, len(z))).round().astype(int))]
    return {"features": list(FEATURES), "scale": list(SCALE), "neutral": np.round(ref, 6).tolist(),
            "keep_fps": KEEP_FPS if times is not None else None, "z": np.round(z, DECIMALS).tolist()}


def read_recording(entry, where: str = RECORDING_KEY) -> tuple[np.ndarray, np.ndarray]:
    """An avatar's :data:`RECORDING_KEY` entry, checked -> (its z (T, F), its scale (F,));
    FacesynthError naming ``where`` for a malformed entry."""
    def bad(what: str):
        return FacesynthError(f"{where}: {what} (re-export the avatar)")

    if not isinstance(entry, dict):
        raise bad(f"expected an object, got {type(entry).__name__}")
    if entry.get("features") != list(FEATURES):
        raise bad(f"its features {entry.get('features')!r} are not the meter's {list(FEATURES)}")
    arrays = {}
    for key, shape in (("scale", (len(FEATURES),)), ("neutral", (len(FEATURES),)), ("z", (-1, len(FEATURES)))):
        try:
            a = np.asarray(entry.get(key))
        except ValueError:  # ragged rows
            a = np.asarray(None)
        if a.dtype.kind not in "iuf":
            raise bad(f"{key} is not an array of numbers")
        a = a.astype(np.float64)
        if a.ndim != len(shape) or any(w != -1 and n != w for n, w in zip(a.shape, shape, strict=False)) or not a.size:
            want = " x ".join("T" if w == -1 else str(w) for w in shape)
            raise bad(f"{key} has shape {' x '.join(map(str, a.shape))}, expected {want} (T >= 1)")
        if not np.isfinite(a).all():
            raise bad(f"{key} has values that are not finite")
        arrays[key] = a
    if not (arrays["scale"] > 0).all():
        raise bad("scale has values that are not positive")
    return arrays["z"], arrays["scale"]


def driver_reach(entry, driver: np.ndarray, driver_neutral: np.ndarray) -> np.ndarray | float:
    """How well an avatar's recording (its :data:`RECORDING_KEY` entry) reaches a driver's
    expression: ``driver`` (478, 2) or (T, 478, 2) tracker points, ``driver_neutral`` (478, 2) the
    driver's neutral; the driver's z ``(features(driver) - features(driver_neutral)) / scale``
    reached by the recording's z (:func:`reach` with :data:`DRIVE_REACH`). A float, or (T,); NaN
    for a frame whose features are not finite."""
    rec, scale = read_recording(entry)
    d, n = np.asarray(driver, np.float64), np.asarray(driver_neutral, np.float64)
    if d.shape[-2:] != (N_POINTS, 2) or d.ndim not in (2, 3) or n.shape != (N_POINTS, 2):
        raise FacesynthError(f"driver_reach: the driver {d.shape} and its neutral {n.shape} must be 478-point frames ((T,) 478 x 2)")
    with np.errstate(invalid="ignore", divide="ignore"):  # a degenerate face: NaN
        z = (features(d.reshape(-1, N_POINTS, 2)) - features(n[None])[0]) / scale
    ok = np.isfinite(z).all(1)
    out = np.full(len(z), np.nan)
    if ok.any():
        out[ok] = reach(rec, z[ok], DRIVE_REACH)
    return float(out[0]) if d.ndim == 2 else out


def heldout_coverage(train_points: np.ndarray, drive_points: np.ndarray) -> float:
    """The meter with other frames than the prior as the shapes to render: how well a clip's
    training frames reach its held-out (or a driver's) frames, each from its own median."""
    tr, dr = features(train_points), features(drive_points)
    return float(reach(to_z(tr, np.median(tr, 0)), to_z(dr, np.median(tr, 0))).mean())


def coverage(prompts: list[dict]) -> dict:
    """``prompts``: ``[{"id", "directions": [...], "points": [(478, 2) array or None per frame]}]``
    (the first prompt with no directions is the neutral) -> ``{"prompts": {id: coverage},
    "directions": {name: coverage on every frame}, "overall": mean of the directions,
    "self_reach": :func:`self_reach` of every frame with a face, prompt after prompt,
    "missing": [ids of the prompts below WEAK, in order]}``."""
    per = []
    for p in prompts:
        pts = [np.asarray(x, np.float64).reshape(-1, 2) for x in p["points"] if x is not None]
        per.append((p, features(np.stack(pts)) if pts else np.zeros((0, len(FEATURES)))))
    every = np.concatenate([f for _, f in per]) if per else np.zeros((0, len(FEATURES)))
    neutral_feats = next((f for p, f in per if not p["directions"] and len(f)), every)
    if len(neutral_feats) == 0:
        return {"prompts": {p["id"]: 0.0 for p in prompts}, "directions": {d: 0.0 for d in DIRECTIONS}, "overall": 0.0,
                "self_reach": 0.0, "missing": [p["id"] for p in prompts]}
    neutral = np.median(neutral_feats, axis=0)
    out = {}
    for p, f in per:
        if p["directions"]:
            out[p["id"]] = float(np.mean([direction_coverage(f, neutral, d) for d in p["directions"]]))
        else:
            out[p["id"]] = len(f) / max(1, len(p["points"]))
    dirs = {d: direction_coverage(every, neutral, d) for d in DIRECTIONS}
    return {"prompts": out, "directions": dirs, "overall": float(np.mean(list(dirs.values()))), "self_reach": self_reach(every),
            "missing": [p["id"] for p in prompts if out[p["id"]] < WEAK]}
