"""MPEG-4 facial animation parameters (FAPs) measured on iBUG 68-point landmarks, and
their inverse (FAPs -> landmarks of another face).

References
----------
ISO/IEC 14496-2 (MPEG-4 Visual), Annex C: facial animation; I. S. Pandzic, R. Forchheimer
(eds.), "MPEG-4 Facial Animation: The Standard, Implementation and Applications", Wiley 2002.

Feature points (FPs)
--------------------
Each MPEG-4 FP used here is the mean of one or more iBUG landmarks (0-based). "Left" and
"right" are the *subject's*: the subject's left is the image's right (+x) for a frontal
face. The pupils are the means of the six eye points.

====  =============================  ==============
FP    description                    iBUG landmarks
====  =============================  ==============
2.1   bottom of chin                 8
2.2   inner upper lip, middle        62
2.3   inner lower lip, middle        66
2.4   inner lip corner, left         64
2.5   inner lip corner, right        60
2.6   inner upper lip, left middle   63
2.7   inner upper lip, right middle  61
2.8   inner lower lip, left middle   65
2.9   inner lower lip, right middle  67
3.1   upper eyelid, left             43, 44
3.2   upper eyelid, right            37, 38
3.3   lower eyelid, left             46, 47
3.4   lower eyelid, right            40, 41
3.5   pupil, left                    42-47
3.6   pupil, right                   36-41
4.1   eyebrow inner, left            22
4.2   eyebrow inner, right           21
4.3   eyebrow middle, left           24
4.4   eyebrow middle, right          19
4.5   eyebrow outer, left            26
4.6   eyebrow outer, right           17
8.1   outer upper lip, middle        51
8.2   outer lower lip, middle        57
8.3   outer lip corner, left         54
8.4   outer lip corner, right        48
8.5   outer upper lip, left middle   52, 53
8.6   outer upper lip, right middle  49, 50
8.7   outer lower lip, left middle   55, 56
8.8   outer lower lip, right middle  58, 59
9.1   nostril, left                  35
9.2   nostril, right                 31
9.15  nose, bottom middle            33
====  =============================  ==============

FAP units (FAPUs), from the neutral face, each = distance / 1024
------------------------------------------------------------------
ES  eye separation (pupil 3.5 to pupil 3.6); ENS eye-nose separation (pupil line to
9.15, along the face's vertical); MNS mouth-nose separation (9.15 to 2.2, vertical);
MW mouth width (8.3 to 8.4); IRISD iris diameter (by the standard's definition the
upper-to-lower eyelid distance 3.1-3.3 / 3.2-3.4 in the neutral face, mean of both eyes).

Axes and signs
--------------
The face frame comes from the neutral face: ``x`` = unit vector from pupil 3.6 to 3.5
(towards the subject's left), ``down`` = ``x`` turned 90 degrees (image y for an
upright face). A FAP's value is the displacement of its FP along its axis, with the
sign of its direction (left = +x, right = -x, down = +down, up = -down), divided by its
FAPU. Head motion is removed first: each frame is similarity-aligned to the neutral
face on the rigid points ``RIGID_POINTS`` (nose bridge and tip, nose base, eye corners).
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, similarity_fit
from facesynth.landmarks import FAP_ANCHORS, N_LANDMARKS, RIGID_FAP

FEATURE_POINTS: dict[str, tuple[int, ...]] = {
    "2.1": (8,), "2.2": (62,), "2.3": (66,), "2.4": (64,), "2.5": (60,), "2.6": (63,), "2.7": (61,),
    "2.8": (65,), "2.9": (67,), "3.1": (43, 44), "3.2": (37, 38), "3.3": (46, 47), "3.4": (40, 41),
    "3.5": (42, 43, 44, 45, 46, 47), "3.6": (36, 37, 38, 39, 40, 41), "4.1": (22,), "4.2": (21,),
    "4.3": (24,), "4.4": (19,), "4.5": (26,), "4.6": (17,), "8.1": (51,), "8.2": (57,), "8.3": (54,),
    "8.4": (48,), "8.5": (52, 53), "8.6": (49, 50), "8.7": (55, 56), "8.8": (58, 59), "9.1": (35,),
    "9.2": (31,), "9.15": (33,),
}

# (MPEG-4 FAP number, name, feature point, direction of positive values, unit)
FAP_TABLE: tuple[tuple[int, str, str, str, str], ...] = (
    (3, "open_jaw", "2.1", "down", "MNS"),
    (4, "lower_t_midlip", "2.2", "down", "MNS"),
    (5, "raise_b_midlip", "2.3", "up", "MNS"),
    (6, "stretch_l_cornerlip", "2.4", "left", "MW"),
    (7, "stretch_r_cornerlip", "2.5", "right", "MW"),
    (8, "lower_t_lip_lm", "2.6", "down", "MNS"),
    (9, "lower_t_lip_rm", "2.7", "down", "MNS"),
    (10, "raise_b_lip_lm", "2.8", "up", "MNS"),
    (11, "raise_b_lip_rm", "2.9", "up", "MNS"),
    (12, "raise_l_cornerlip", "2.4", "up", "MNS"),
    (13, "raise_r_cornerlip", "2.5", "up", "MNS"),
    (15, "shift_jaw", "2.1", "right", "MW"),
    (19, "close_t_l_eyelid", "3.1", "down", "IRISD"),
    (20, "close_t_r_eyelid", "3.2", "down", "IRISD"),
    (21, "close_b_l_eyelid", "3.3", "up", "IRISD"),
    (22, "close_b_r_eyelid", "3.4", "up", "IRISD"),
    (31, "raise_l_i_eyebrow", "4.1", "up", "ENS"),
    (32, "raise_r_i_eyebrow", "4.2", "up", "ENS"),
    (33, "raise_l_m_eyebrow", "4.3", "up", "ENS"),
    (34, "raise_r_m_eyebrow", "4.4", "up", "ENS"),
    (35, "raise_l_o_eyebrow", "4.5", "up", "ENS"),
    (36, "raise_r_o_eyebrow", "4.6", "up", "ENS"),
    (37, "squeeze_l_eyebrow", "4.1", "right", "ES"),
    (38, "squeeze_r_eyebrow", "4.2", "left", "ES"),
    (51, "lower_t_midlip_o", "8.1", "down", "MNS"),
    (52, "raise_b_midlip_o", "8.2", "up", "MNS"),
    (53, "stretch_l_cornerlip_o", "8.3", "left", "MW"),
    (54, "stretch_r_cornerlip_o", "8.4", "right", "MW"),
    (55, "lower_t_lip_lm_o", "8.5", "down", "MNS"),
    (56, "lower_t_lip_rm_o", "8.6", "down", "MNS"),
    (57, "raise_b_lip_lm_o", "8.7", "up", "MNS"),
    (58, "raise_b_lip_rm_o", "8.8", "up", "MNS"),
    (59, "raise_l_cornerlip_o", "8.3", "up", "MNS"),
    (60, "raise_r_cornerlip_o", "8.4", "up", "MNS"),
    (61, "stretch_l_nose", "9.1", "left", "ENS"),
    (62, "stretch_r_nose", "9.2", "right", "ENS"),
)
FAP_NAMES = tuple(row[1] for row in FAP_TABLE)
N_FAPS = len(FAP_TABLE)
FAPU_NAMES = ("ES", "ENS", "MNS", "MW", "IRISD")
RIGID_POINTS = RIGID_FAP  # no FAP moves them: the head pose is fitted on them
# Landmarks held still by the inverse (besides the FAP-driven ones) when interpolating the rest.
ANCHOR_POINTS = FAP_ANCHORS

_FP_IDS = tuple(FEATURE_POINTS)
_FP_MATRIX = np.zeros((len(_FP_IDS), N_LANDMARKS))
for _i, _fp in enumerate(_FP_IDS):
    _FP_MATRIX[_i, list(FEATURE_POINTS[_fp])] = 1.0 / len(FEATURE_POINTS[_fp])
_DIR = {"left": (0, 1.0), "right": (0, -1.0), "down": (1, 1.0), "up": (1, -1.0)}
_FAP_FP = np.array([_FP_IDS.index(r[2]) for r in FAP_TABLE])
_FAP_AXIS = np.array([_DIR[r[3]][0] for r in FAP_TABLE])
_FAP_SIGN = np.array([_DIR[r[3]][1] for r in FAP_TABLE])
_FAP_UNIT = np.array([FAPU_NAMES.index(r[4]) for r in FAP_TABLE])
_DRIVEN = sorted({lm for fp in set(r[2] for r in FAP_TABLE) for lm in FEATURE_POINTS[fp]})


def _fp(landmarks: np.ndarray) -> np.ndarray:
    """(..., 68, 2) landmarks -> (..., n_fp, 2) feature points."""
    return np.einsum("fl,...lc->...fc", _FP_MATRIX, np.asarray(landmarks, np.float64))


def face_axes(neutral: np.ndarray) -> np.ndarray:
    """(2, 2) rows: unit ``x`` (towards the subject's left) and ``down`` of a (68, 2) face."""
    fp = _fp(neutral)
    x = fp[_FP_IDS.index("3.5")] - fp[_FP_IDS.index("3.6")]
    n = np.linalg.norm(x)
    if not n > 0:
        raise FacesynthError("neutral landmarks: the two pupils coincide; cannot define the face axes")
    x = x / n
    return np.stack([x, np.array([-x[1], x[0]])])


def fapu(neutral: np.ndarray) -> np.ndarray:
    """FAP units of a (68, 2) neutral face: (5,) float64 in pixels / 1024, order ``FAPU_NAMES``."""
    neutral = _check(neutral, "neutral landmarks")[0]
    fp = {k: v for k, v in zip(_FP_IDS, _fp(neutral), strict=True)}
    down = face_axes(neutral)[1]
    pupils = 0.5 * (fp["3.5"] + fp["3.6"])
    units = np.array([
        np.linalg.norm(fp["3.5"] - fp["3.6"]),
        (fp["9.15"] - pupils) @ down,
        (fp["2.2"] - fp["9.15"]) @ down,
        np.linalg.norm(fp["8.3"] - fp["8.4"]),
        0.5 * (np.linalg.norm(fp["3.1"] - fp["3.3"]) + np.linalg.norm(fp["3.2"] - fp["3.4"])),
    ]) / 1024.0
    if not (units > 0).all():
        bad = [n for n, u in zip(FAPU_NAMES, units, strict=True) if not u > 0]
        raise FacesynthError(
            f"neutral landmarks: FAP units {bad} are not positive (eyes closed, mouth above the nose or "
            "a degenerate face?); choose another neutral frame"
        )
    return units


def head_pose(landmarks: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Similarity transforms (N, 2, 3) mapping the neutral face onto each frame, fitted on
    ``RIGID_POINTS`` (so expressions do not bias them)."""
    lm = _check(landmarks, "landmarks")
    rigid = list(RIGID_POINTS)
    return similarity_fit(np.asarray(neutral, np.float64)[rigid][None], lm[:, rigid].astype(np.float64))


def align_to_neutral(landmarks: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Remove head motion: (N, 68, 2) frames similarity-aligned onto the neutral (68, 2)."""
    lm = _check(landmarks, "landmarks").astype(np.float64)
    rigid = list(RIGID_POINTS)
    m = similarity_fit(lm[:, rigid], np.asarray(neutral, np.float64)[rigid][None])
    return apply_affine(lm, m)


def compute_faps(landmarks: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """FAPs of (N, 68, 2) frames relative to the subject's (68, 2) neutral face.

    Returns
    -------
    np.ndarray
        float32 (N, N_FAPS), columns in ``FAP_NAMES`` order, in FAPU (1/1024 of the unit).
    """
    neutral = _check(neutral, "neutral landmarks")[0].astype(np.float64)
    units, axes = fapu(neutral), face_axes(neutral)
    d = _fp(align_to_neutral(landmarks, neutral)) - _fp(neutral)  # (N, n_fp, 2)
    comp = d @ axes.T  # (N, n_fp, 2): (x, down) components
    vals = comp[:, _FAP_FP, _FAP_AXIS] * _FAP_SIGN / units[_FAP_UNIT]
    return vals.astype(np.float32)


def faps_to_landmarks(neutral: np.ndarray, faps: np.ndarray) -> np.ndarray:
    """The inverse: a person's (68, 2) neutral face + (N, N_FAPS) FAPs -> (N, 68, 2)
    expressive landmarks in the neutral face's head pose, scaled by *this* face's FAPUs.

    The landmarks of each FAP's feature point move by the FAP displacement (components
    along axes without a FAP stay zero); ``ANCHOR_POINTS`` stay still; every other
    landmark (jaw line, brow middles, nose base) moves by thin-plate-spline interpolation
    of those displacements over the neutral face. ``compute_faps`` of the result returns
    ``faps`` (the anchors carry the rigid alignment).
    """
    neutral = _check(neutral, "neutral landmarks")[0].astype(np.float64)
    return (neutral[None] + fap_displacements(neutral, faps)).astype(np.float32)


def fap_displacements(neutral: np.ndarray, faps: np.ndarray) -> np.ndarray:
    """Landmark displacements (N, 68, 2) float64 of :func:`faps_to_landmarks` (without the
    float32 rounding). They are *linear* in the FAPs: ``fap_displacements(neutral,
    np.eye(N_FAPS))`` is the exact Jacobian, used by the ONNX export."""
    neutral = _check(neutral, "neutral landmarks")[0].astype(np.float64)
    f = np.asarray(faps, np.float64)
    if f.ndim == 1:
        f = f[None]
    if f.ndim != 2 or f.shape[1] != N_FAPS:
        raise FacesynthError(f"faps must have shape (N, {N_FAPS}), got {f.shape}")
    units, axes = fapu(neutral), face_axes(neutral)
    comp = np.zeros((len(f), len(_FP_IDS), 2))
    np.add.at(comp, (slice(None), _FAP_FP, _FAP_AXIS), f * _FAP_SIGN * units[_FAP_UNIT])
    disp_fp = comp @ axes  # back to image axes, (N, n_fp, 2)
    disp = np.zeros((len(f), N_LANDMARKS, 2))
    for fp_i, fp in enumerate(_FP_IDS):
        if fp_i in set(_FAP_FP.tolist()):
            disp[:, list(FEATURE_POINTS[fp])] = disp_fp[:, fp_i, None]
    interp, rest, ctrl = _interpolation(neutral)
    disp[:, rest] = np.einsum("rc,ncd->nrd", interp, disp[:, ctrl])
    return disp


def _interpolation(neutral: np.ndarray) -> tuple[np.ndarray, list, list]:
    """Linear thin-plate-spline map from control-point to free-point displacements:
    (n_free, n_ctrl) weights, free and control indices.

    The inner-lip points are left out of the controls (they coincide in a closed-mouth
    neutral face, which makes interpolation singular); a small smoothing term keeps the
    system regular if other controls coincide (dlib's integer landmarks).
    """
    from scipy.interpolate import RBFInterpolator

    ctrl = sorted(set(_DRIVEN) | set(ANCHOR_POINTS))
    rest = [i for i in range(N_LANDMARKS) if i not in ctrl]
    basis = [i for i in ctrl if not 60 <= i <= 67]
    scale = np.linalg.norm(neutral.max(0) - neutral.min(0))
    pts = (neutral - neutral.mean(0)) / scale
    rbf = RBFInterpolator(pts[basis], np.eye(len(basis)), kernel="thin_plate_spline", smoothing=1e-6)
    weights = np.zeros((len(rest), len(ctrl)))
    weights[:, [ctrl.index(i) for i in basis]] = rbf(pts[rest])
    return weights, rest, ctrl


def _check(landmarks: np.ndarray, where: str) -> np.ndarray:
    lm = np.asarray(landmarks)
    if lm.ndim == 2:
        lm = lm[None]
    if lm.ndim != 3 or lm.shape[1:] != (N_LANDMARKS, 2):
        raise FacesynthError(f"{where}: expected (N, 68, 2) or (68, 2) iBUG landmarks, got shape {lm.shape}")
    if not np.isfinite(lm).all():
        raise FacesynthError(f"{where}: landmarks contain NaN/inf")
    return lm
