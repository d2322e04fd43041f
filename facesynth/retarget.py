"""Landmark retargeting: carry a driver's *motion* (expression and head movement relative
to the driver's own neutral face) onto an avatar's neutral face, so that the avatar keeps
its own face shape and place in its own frame (numpy only: used by the torch-free runtime,
:class:`facesynth.runtime.Reenactor`, and by ERI's expression transfer).

Per driver frame ``D`` with the driver's neutral ``D_n`` and the avatar's neutral ``A_n``
(both (P, 2) frame pixels in one landmark scheme: ``ibug68``, P = 68, or ``mediapipe478``,
P = 478; the FAP units and face axes are measured on their iBUG-68 view,
:meth:`LandmarkScheme.to_ibug68`):

1. head pose ``P``: the similarity mapping ``D_n`` onto ``D``, fitted on the rigid points
   no expression moves (:data:`facesynth.faps.RIGID_POINTS`: nose bridge and tip, eye
   corners), as ERI's FAPs do;
2. expression: ``D`` aligned back onto ``D_n`` (``P^-1``) minus ``D_n``: a displacement per
   point, split into the driver's face axes (``x`` from pupil to pupil, ``down``);
3. scaling: the MPEG-4 FAP idea extended to every point. Each point and axis has a FAP
   unit (:data:`POINT_UNITS`: mouth and jaw by mouth width / mouth-nose separation, eyes
   by eye separation / eyelid opening, brows and nose by eye separation / eye-nose
   separation; a 478-point mesh point outside those regions takes the units of the nearest
   point in them on the avatar's neutral; with irises, IRISD is the iris diameter,
   :func:`iris_diameter`), and its displacement is multiplied by avatar unit / driver unit
   (:func:`facesynth.faps.fapu` of both neutrals), then put on the avatar's face axes and
   added to ``A_n``; on the FAP feature points this is exactly ``faps_to_landmarks(A_n,
   compute_faps(D, D_n))`` along the FAP axes. Facing eyelid points, and facing inner-lip
   points, that would cross (an upper one below its lower one along the avatar's ``down``
   axis) meet at their midpoint instead (:func:`closing_pairs`): a driver whose neutral
   mouth is open, closing it, would otherwise fold the lips of an avatar whose neutral mouth
   is closed (docs/reenact.md), and a blink on nearly shut eyes the eyelids;
4. head motion (``motion="relative"``): ``C P C^-1`` applied to the result, with ``C`` the
   similarity from ``D_n`` to ``A_n`` (rigid points): the driver's rotation, scale change
   and translation (in avatar pixels) around the avatar's own neutral placement. How far it
   moves the head (the rigid points' centroid) is bounded, when the shape space has the
   avatar's own range (``ShapeSpace.shift_range``, :func:`head_shifts`), to that range
   widened by ``SHIFT_WIDEN`` times its width on each side and at least ``SHIFT_FLOOR``
   outer-eye-corner distances each way (:func:`shift_bounds`): the avatar's frame has
   nothing beyond its own head's travel, and a driver that wanders far would otherwise
   stretch a neck out of the frame's bottom rows (docs/reenact.md);
5. the shape is projected onto the avatar's shape PCA (similarity-aligned to its mean), its
   parameters clamped to +-k sqrt(lambda) and then scaled down, as a vector, to the largest
   norm (in units of those limits) the avatar's own training frames have, and its part
   outside the components scaled down to the largest they have (:class:`ShapeSpace`), so that it
   stays a face the model was trained on (a driver's head turn on an avatar that never
   turned, a mouth shape it never made: docs/reenact.md, "Shapes no further from the
   avatar's own"). The eyelids are then put back as they were relative to their eye
   corners (the corners stay clamped): a clip's shape PCA spends its few components on head
   turns and the mouth, so the clamp would otherwise cut a driver's blinks and wide eyes
   (docs/reenact.md measures the eye-opening correlation with and without). Each eye's
   opening is then capped at the widest the avatar's own training frames open that eye
   (``ShapeSpace.eye_open_max``): the eye, lids and iris, is squashed towards the line
   through its corners until it is no wider, so that a driver whose neutral has narrower
   eyes than its usual ones does not leave the avatar staring with stretched lids
   (docs/reenact.md, "Eyes no wider than the avatar's own"); blinks pass unchanged. The
   clamped shape can cross the inner lips again (a mouth the PCA does not reach): they are
   uncrossed once more as in step 3, along the avatar's down axis moved with the head.

``motion="absolute"`` returns the driver's landmarks unchanged (the behaviour before
retargeting; for self-driving and tests).
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.faps import FAPU_NAMES, RIGID_POINTS, face_axes, fapu
from facesynth.geometry import similarity_fit
from facesynth.landmarks import (
    IBUG68,
    LandmarkScheme,
    eye_lids,
    facing_pairs,
    ibug68_view,
    inter_ocular,
)
from facesynth.shape_space import RETARGET_SCHEMES, ShapeSpace, retarget_scheme

MOTIONS = ("relative", "absolute")
SHIFT_WIDEN = 0.5  # the head's travel bound: the avatar's own range widened by this times its width,
SHIFT_FLOOR = 0.3  # and at least this many outer-eye-corner distances each way (module docstring, step 4)
# regions -> the FAP units of their (x, down) motion
_REGION_UNITS = (("jaw", "MW", "MNS"), ("mouth", "MW", "MNS"), ("eyes", "ES", "IRISD"), ("irises", "ES", "IRISD"),
                 ("brows", "ES", "ENS"), ("nose", "ES", "ENS"))


def point_units(scheme: LandmarkScheme, neutral: np.ndarray | None = None) -> np.ndarray:
    """int (P, 2): the FAPU (index into FAPU_NAMES) scaling each point's (x, down) motion, from
    the scheme's regions; points in none of them (a mesh's cheeks and forehead) take the units
    of the nearest region point on ``neutral`` (P, 2)."""
    u = {n: i for i, n in enumerate(FAPU_NAMES)}
    out = np.full((scheme.n_points, 2), -1, np.int64)
    for region, ux, uy in _REGION_UNITS:
        if region in scheme.regions:
            out[scheme.region(region)] = (u[ux], u[uy])
    free = np.flatnonzero(out[:, 0] < 0)
    if len(free):
        if neutral is None:
            raise FacesynthError(f"{scheme.name}: {len(free)} points outside the FAP regions need a neutral face for their units")
        labelled = np.flatnonzero(out[:, 0] >= 0)
        d = np.linalg.norm(np.asarray(neutral, np.float64)[free, None] - np.asarray(neutral, np.float64)[None, labelled], axis=-1)
        out[free] = out[labelled[d.argmin(1)]]
    return out


POINT_UNITS = point_units(IBUG68)


def rigid_points(scheme: LandmarkScheme) -> list[int]:
    """The scheme's points at :data:`RIGID_POINTS` (through its iBUG-68 correspondence)."""
    return [p for i in RIGID_POINTS for p in scheme.ibug68[i]]


def eyelid_pairs(scheme: LandmarkScheme) -> tuple[np.ndarray, np.ndarray]:
    """(upper, lower) facing eyelid points of both eyes (:func:`facesynth.landmarks.eye_lids`:
    each eye's contour is a ring from one corner over the upper lid to the other corner
    (index n / 2) and back, so point k faces n - k)."""
    (ru, rl), (lu, ll) = eye_lids(scheme)
    return np.concatenate([ru, lu]), np.concatenate([rl, ll])


def closing_pairs(scheme: LandmarkScheme) -> tuple[np.ndarray, np.ndarray]:
    """(upper, lower) facing points that close onto each other: the eyelids of both eyes
    (:func:`eyelid_pairs`) and the inner lips (the ``inner_lips`` ring, corner to corner over
    the upper lip and back over the lower one)."""
    lids, lips = eyelid_pairs(scheme), facing_pairs(scheme.region("inner_lips"))
    return np.concatenate([lids[0], lips[0]]), np.concatenate([lids[1], lips[1]])


def iris_diameter(scheme: LandmarkScheme, face: np.ndarray) -> float:
    """Mean iris diameter (pixels) of a (P, 2) face of a scheme with irises (centre, then
    boundary points): twice the mean centre-to-boundary distance, over both eyes. MPEG-4
    takes the neutral's eyelid distance for IRISD (no iris points); a downcast neutral makes
    that tiny, and every eyelid motion of the driver then shrinks on the avatar."""
    out = []
    for side in ("right_iris", "left_iris"):
        idx = scheme.region(side)
        out.append(2.0 * np.linalg.norm(face[idx[1:]] - face[idx[0]], axis=-1).mean())
    return float(np.mean(out))


def head_shifts(scheme: LandmarkScheme, neutral: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(N, 2) how far (frame pixels) (N, P, 2) ``frames`` move the head from the (P, 2)
    ``neutral``: their rigid points' centroid less the neutral's."""
    rigid = rigid_points(scheme)
    return np.asarray(frames, np.float64)[:, rigid].mean(1) - np.asarray(neutral, np.float64)[rigid].mean(0)


def shift_bounds(space: ShapeSpace | None, neutral: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) (2,) each: the bound on how far the head moves from the avatar's (P, 2)
    ``neutral`` (module docstring, step 4), or None when ``space`` has no ``shift_range``."""
    if space is None or space.shift_range is None:
        return None
    lo, hi = space.shift_range
    floor = SHIFT_FLOOR * float(inter_ocular(ibug68_view(neutral)))
    return np.minimum(lo - SHIFT_WIDEN * (hi - lo), -floor), np.maximum(hi + SHIFT_WIDEN * (hi - lo), floor)


def eye_open(landmarks: np.ndarray) -> np.ndarray:
    """Mean eyelid gap (the facing eyelid points of both eyes, :func:`eyelid_pairs`: 37-41,
    38-40, 43-47, 44-46) / inter-ocular distance: (N, 68, 2) -> (N,)."""
    lm = np.asarray(landmarks, np.float64)
    up, lo = eyelid_pairs(IBUG68)
    gap = np.linalg.norm(lm[..., up, :] - lm[..., lo, :], axis=-1).mean(-1)
    return gap / inter_ocular(lm)


class Retargeter:
    """Driver landmarks -> avatar landmarks (module docstring: steps 1-5).

    Parameters
    ----------
    avatar_neutral : (P, 2) the avatar's neutral face, its frame pixels
    driver_neutral : (P, 2) the driver's neutral face, the driver's frame pixels
    shape_space : ShapeSpace, optional; projection and clamping (step 5), skipped if None
    motion : "relative" (default) or "absolute" (the driver's landmarks, unchanged)
    head_motion : with "relative": apply the driver's head motion (step 4); False keeps the
        avatar's neutral placement (ERI's expression transfer renders in the target's pose)

    scheme : the landmark scheme of all of them (:data:`RETARGET_SCHEMES`; the shape space's)

    ``__call__``: (N, P, 2) or (P, 2) driver frame landmarks -> float32 (N, P, 2).
    """

    def __init__(self, avatar_neutral, driver_neutral, shape_space: ShapeSpace | None = None, motion: str = "relative",
                 head_motion: bool = True, scheme: str = "ibug68"):
        if motion not in MOTIONS:
            raise FacesynthError(f"motion must be one of {MOTIONS}, got {motion!r}")
        sch = retarget_scheme(scheme)
        if shape_space is not None and shape_space.scheme != sch.name:
            raise FacesynthError(f"retargeting {sch.name} landmarks with a shape space of {shape_space.scheme}")
        self.scheme = sch
        self.motion = motion
        self.head_motion = bool(head_motion)
        self.avatar_neutral = _one_face(avatar_neutral, "avatar neutral", sch.n_points)
        self.driver_neutral = _one_face(driver_neutral, "driver neutral", sch.n_points)
        self.shape_space = shape_space
        rigid = rigid_points(sch)
        self._rigid = rigid
        dn = self.driver_neutral[rigid]
        self._dn_mu = dn.mean(0)
        self._rigid_avg = np.full(len(rigid), 1.0 / len(rigid))
        dc = dn - self._dn_mu
        # pose fit (driver neutral -> frame, rigid points): [a, b] = frame_rigid.ravel() @ w
        self._pose_w = np.stack([dc.reshape(-1), np.stack([-dc[:, 1], dc[:, 0]], 1).reshape(-1)], 1) / float(np.vdot(dc, dc))
        a68, d68 = ibug68_view(self.avatar_neutral), ibug68_view(self.driver_neutral)
        ratio = fapu(a68) / fapu(d68)  # (5,)
        if "irises" in sch.regions:  # IRISD from the irises themselves (see iris_diameter)
            ratio[FAPU_NAMES.index("IRISD")] = iris_diameter(sch, self.avatar_neutral) / iris_diameter(sch, self.driver_neutral)
        axes_d, axes_a = face_axes(d68), face_axes(a68)
        self._down = axes_a[1]
        self._shut_up, self._shut_lo = closing_pairs(sch)
        # expression: disp_a = ((disp_d @ axes_d.T) * ratio_p) @ axes_a, one (2, 2) map per point
        units = POINT_UNITS if sch.name == "ibug68" else point_units(sch, self.avatar_neutral)
        scale = ratio[units]  # (P, 2)
        e = np.einsum("ij,pj,jk->pik", axes_d.T, scale, axes_a)  # (P, 2, 2)
        self._e0, self._e1 = np.ascontiguousarray(e[:, 0]), np.ascontiguousarray(e[:, 1])
        self.unit_ratio = dict(zip(FAPU_NAMES, ratio.round(4).tolist(), strict=True))
        c = similarity_fit(self.driver_neutral[rigid], self.avatar_neutral[rigid])  # driver -> avatar
        self._c_lin, self._c_t = c[:, :2], c[:, 2]
        self._c_inv_lin = np.linalg.inv(self._c_lin)
        self._centre = self.avatar_neutral[rigid].mean(0)
        self.shift_bounds = shift_bounds(shape_space, self.avatar_neutral)  # (lo, hi) or None

    def _uncrossed(self, expr: np.ndarray, down: np.ndarray) -> np.ndarray:
        """Eyelids and inner lips (:func:`closing_pairs`) that would cross (an upper point
        below its lower one along the unit axis ``down`` (2,)) meet at their midpoint instead;
        (P, 2) -> (P, 2), unchanged where none crosses (module docstring, steps 3 and 5)."""
        du, dl = expr[self._shut_up] @ down, expr[self._shut_lo] @ down
        cross = du > dl
        if not cross.any():
            return expr
        out = expr.copy()
        mid = 0.5 * (du + dl)
        out[self._shut_up[cross]] += np.outer(mid[cross] - du[cross], down)
        out[self._shut_lo[cross]] += np.outer(mid[cross] - dl[cross], down)
        return out

    def pose(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The driver's head pose of one (P, 2) frame: the similarity (2x2, 2) mapping the
        driver's neutral onto it, fitted on the rigid points."""
        r = frame[self._rigid]
        ca, sa = r.reshape(-1) @ self._pose_w
        lin = np.array([[ca, -sa], [sa, ca]])
        return lin, self._rigid_avg @ r - lin @ self._dn_mu

    def one(self, frame: np.ndarray) -> np.ndarray:
        """One (P, 2) driver frame -> float64 (P, 2) avatar landmarks (relative motion)."""
        lin, t = self.pose(frame)
        inv_t = lin / (lin[0, 0] ** 2 + lin[1, 0] ** 2)  # transpose of the similarity's inverse
        disp = (frame - t) @ inv_t - self.driver_neutral  # expression in the driver's neutral frame
        expr = self.avatar_neutral + disp[:, 0:1] * self._e0 + disp[:, 1:2] * self._e1
        expr = self._uncrossed(expr, self._down)
        if not self.head_motion:
            return expr if self.shape_space is None else self._uncrossed(self.shape_space.project(expr), self._down)
        # head motion C P C^-1 around the avatar's neutral placement
        m_lin = self._c_lin @ lin @ self._c_inv_lin
        m_t = self._c_lin @ (t - lin @ (self._c_inv_lin @ self._c_t)) + self._c_t
        if self.shift_bounds is not None:  # the head's travel, bounded (module docstring, step 4)
            shift = m_lin @ self._centre + m_t - self._centre
            m_t = m_t + np.clip(shift, *self.shift_bounds) - shift
        out = expr @ m_lin.T + m_t
        if self.shape_space is None:
            return out
        down = m_lin @ self._down  # the avatar's down axis, moved with the head
        return self._uncrossed(self.shape_space.project(out), down / np.linalg.norm(down))

    def __call__(self, driver) -> np.ndarray:
        d = np.asarray(driver, np.float64)
        if d.ndim == 2:
            d = d[None]
        n = self.scheme.n_points
        if d.ndim != 3 or d.shape[1:] != (n, 2):
            raise FacesynthError(f"driver landmarks: expected (N, {n}, 2) {self.scheme.name} landmarks, got {np.shape(driver)}")
        if self.motion == "absolute":
            return d.astype(np.float32)
        return np.stack([self.one(f) for f in d]).astype(np.float32)


def _one_face(x, where: str, n: int) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.shape != (n, 2) or not np.isfinite(a).all():
        raise FacesynthError(f"{where}: expected finite ({n}, 2) landmarks, got shape {a.shape}")
    return a


__all__ = ["MOTIONS", "POINT_UNITS", "RETARGET_SCHEMES", "SHIFT_FLOOR", "SHIFT_WIDEN", "Retargeter", "ShapeSpace", "eye_open",
           "head_shifts", "point_units", "shift_bounds"]
