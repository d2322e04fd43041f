"""An avatar's shape space for retargeting (numpy only): the face model's shape PCA, onto
which retargeted shapes are projected and clamped so that they stay faces the model was
trained on (:mod:`facesynth.retarget`, step 5), and the landmark schemes retargeting takes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.landmarks import LandmarkScheme, eye_openings, get_scheme

RETARGET_SCHEMES = ("ibug68", "mediapipe478")  # schemes whose every point is a face-model point


def retarget_scheme(name: str) -> LandmarkScheme:
    """The registered scheme ``name`` if retargeting supports it, else FacesynthError."""
    if name not in RETARGET_SCHEMES:
        raise FacesynthError(f"retargeting takes {' or '.join(RETARGET_SCHEMES)} landmarks, not {name!r}")
    return get_scheme(name)


def eye_patches(scheme: LandmarkScheme) -> tuple:
    """Per eye: (contour points (the iris too, when the scheme has one), corner, corner)."""
    c = scheme.region("eye_corners")
    out = []
    for side, corners in (("right", c[:2]), ("left", c[2:])):
        idx = scheme.region(f"{side}_eye")
        if f"{side}_iris" in scheme.regions:
            idx = np.concatenate([idx, scheme.region(f"{side}_iris")])
        out.append((idx, int(corners[0]), int(corners[1])))
    return tuple(out)


@dataclass
class ShapeSpace:
    """An avatar's shape PCA (the face model's, in its normalised frame): project shapes onto
    it, clamp their parameters to +-``limit`` and then into the ellipsoid of norm
    ``param_norm_max``, and the rest of them (what the components do not span) to the norm
    ``residual_max``.

    mean : (2P,) float64, components : (K, 2P) orthonormal rows, limit : (K,) (k sqrt(lambda)).
    keep_eyes : after clamping, restore each eye's contour relative to its two corners
        (:mod:`facesynth.retarget`, step 5); False clamps the eyelids with the rest.
    scheme : the landmark scheme (P from it; its eye regions for ``keep_eyes``)
    eye_open_max : (2,) or None: the widest opening of each eye (right, left;
        :func:`facesynth.landmarks.eye_openings`) that a projected shape keeps
        (:mod:`facesynth.retarget`, step 5); None: no cap (models exported without it)
    residual_max : float or None: the largest norm (normalised frame) of a shape's part that
        the components do not span, kept as it is below it and scaled down to it above
        (the largest of the avatar's own training frames, :meth:`norms`); None: kept
        whole (models exported without it)
    param_norm_max : float or None: the largest norm of the clamped parameters in units of
        their limits (``|clip(b, -limit, limit) / limit|``, a Mahalanobis distance over k) that
        a projected shape keeps: beyond it they are scaled down to it, so that the
        components' combination is no further from the mean than the avatar's own most
        extreme training frame (:meth:`norms`; Cootes' D_max bound inside the box); None:
        the box alone (models exported without it)
    shift_range : (2, 2) or None: rows lo, hi of how far (x, y frame pixels) the avatar's own
        training frames move its head from the neutral (the rigid points' centroid), which
        :class:`facesynth.retarget.Retargeter` widens into the bound of a driver's head motion;
        None: no bound (models exported without it)
    """

    mean: np.ndarray
    components: np.ndarray
    limit: np.ndarray
    keep_eyes: bool = True
    scheme: str = "ibug68"
    eye_open_max: np.ndarray | None = None
    residual_max: float | None = None
    shift_range: np.ndarray | None = None
    param_norm_max: float | None = None

    @classmethod
    def from_dict(cls, d: dict, scheme: str = "ibug68") -> "ShapeSpace":
        """From the exported model's ``shape_pca`` metadata: {mean, components, limit}, of ``scheme``."""
        try:
            pca = [np.asarray(d[k], np.float64) for k in ("mean", "components", "limit")]
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise FacesynthError(f"shape_pca metadata: expected mean, components and limit ({exc})") from None
        extra = {}
        for key, scalar in (("eye_open_max", False), ("residual_max", True), ("shift_range", False),
                            ("param_norm_max", True)):  # optional: None when absent (older exports)
            if d.get(key) is not None:
                try:
                    extra[key] = float(d[key]) if scalar else np.asarray(d[key], np.float64)
                except (TypeError, ValueError):
                    raise FacesynthError(f"shape_pca metadata: {key} must be numeric, got {d[key]!r}") from None
        return cls(*pca, scheme=scheme, **extra)

    def to_dict(self) -> dict:
        out = {k: np.round(getattr(self, k), 7).tolist() for k in ("mean", "components", "limit")}
        if self.eye_open_max is not None:
            out["eye_open_max"] = np.round(self.eye_open_max, 7).tolist()
        if self.residual_max is not None:
            out["residual_max"] = round(float(self.residual_max), 9)
        if self.shift_range is not None:
            out["shift_range"] = np.round(self.shift_range, 4).tolist()
        if self.param_norm_max is not None:
            out["param_norm_max"] = round(float(self.param_norm_max), 9)
        return out

    def __post_init__(self):
        sch = retarget_scheme(self.scheme)
        n = sch.n_points
        k = len(self.limit)
        if self.mean.shape != (2 * n,) or self.components.shape != (k, 2 * n):
            raise FacesynthError(f"shape_pca metadata: mean {self.mean.shape}, components {self.components.shape}, limit ({k},) "
                                 f"do not form a shape PCA of {self.scheme} ({n} points)")
        if self.eye_open_max is not None:
            cap = np.asarray(self.eye_open_max, np.float64)
            if cap.shape != (2,) or not np.all(np.isfinite(cap) & (cap > 0)):
                raise FacesynthError(f"shape_pca metadata: eye_open_max must be two positive numbers, got {self.eye_open_max}")
            self.eye_open_max = cap
        if self.residual_max is not None and not (np.isfinite(self.residual_max) and self.residual_max >= 0):
            raise FacesynthError(f"shape_pca metadata: residual_max must be a number >= 0, got {self.residual_max}")
        if self.param_norm_max is not None and not np.all(self.limit > 0):
            raise FacesynthError(f"shape_pca metadata: param_norm_max needs limits > 0, got {np.round(self.limit, 6).tolist()}")
        if self.param_norm_max is not None and not (np.isfinite(self.param_norm_max) and self.param_norm_max >= 0):
            raise FacesynthError(f"shape_pca metadata: param_norm_max must be a number >= 0, got {self.param_norm_max}")
        if self.shift_range is not None:
            r = np.asarray(self.shift_range, np.float64)
            if r.shape != (2, 2) or not np.isfinite(r).all() or (r[0] > r[1]).any():
                raise FacesynthError(f"shape_pca metadata: shift_range must be finite rows lo <= hi of (x, y), got "
                                     f"{self.shift_range}")
            self.shift_range = r
        self._n = n
        self._scheme = sch
        self._eyes = eye_patches(sch)
        mean = self.mean.reshape(n, 2)
        self._mu = mean.mean(0)
        mc = mean - self._mu
        # similarity fit of a shape onto the mean: [a, b] = shape.ravel() @ w / var(shape)
        self._w = np.stack([mc.reshape(-1), np.stack([mc[:, 1], -mc[:, 0]], 1).reshape(-1)], 1)  # (2P, 2)
        self._ct = np.ascontiguousarray(self.components.T)
        self._off = self.mean @ self._ct
        self._avg = np.full(n, 1.0 / n)  # mean as a matmul (faster than .mean at this size)

    def _align(self, x: np.ndarray) -> tuple:
        """A (P, 2) shape similarity-aligned to the mean: (its centroid, ca, sa, the aligned
        shape (P, 2), its parameters b (K,), the part the components do not span (P, 2))."""
        mo = self._avg @ x
        xc = x - mo
        var = float(np.vdot(xc, xc)) or 1.0
        ca, sa = (xc.reshape(-1) @ self._w) / var  # shape -> mean: [[ca, -sa], [sa, ca]] (x - mo) + mu
        aligned = xc @ np.array([[ca, -sa], [sa, ca]]).T + self._mu
        b = aligned.reshape(-1) @ self._ct - self._off
        rest = aligned - (self.mean + b @ self.components).reshape(self._n, 2)
        return mo, ca, sa, aligned, b, rest

    def _clamped(self, b: np.ndarray) -> np.ndarray:
        """(K,) parameters -> clamped to +-limit, then scaled into the ellipsoid of norm
        ``param_norm_max`` (in units of the limits)."""
        c = np.clip(b, -self.limit, self.limit)
        if self.param_norm_max is not None:
            norm = float(np.linalg.norm(c / self.limit))
            if norm > self.param_norm_max:
                c = c * (self.param_norm_max / norm)
        return c

    def norms(self, shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) each, for (N, P, 2) frame-pixel shapes aligned once: the norm of the part the
        components do not span, in the normalised frame (the quantity ``residual_max``
        bounds), and of the box-clamped parameters in units of the limits (the quantity
        ``param_norm_max`` bounds; :meth:`_clamped` without it)."""
        aligned = [self._align(f) for f in np.asarray(shapes, np.float64)]
        rest = np.array([np.linalg.norm(a[5]) for a in aligned])
        b = np.array([a[4] for a in aligned]).reshape(-1, len(self.limit))
        return rest, np.linalg.norm(np.clip(b, -self.limit, self.limit) / self.limit, axis=1)

    def project(self, shapes: np.ndarray) -> np.ndarray:
        """(N, P, 2) or (P, 2) frame-pixel shapes -> the nearest model shapes with clamped
        parameters, in the same frame (float64, same shape)."""
        x = np.asarray(shapes, np.float64)
        if x.ndim == 3:
            return np.stack([self.project(f) for f in x])
        mo, ca, sa, aligned, b, rest = self._align(x)
        # move the shape back inside the box and the ellipsoid along the model's components, and
        # scale what they do not span down to residual_max (what the avatar's own frames have:
        # a driver's head turn on an avatar that never turned, expressions it never made)
        rec = aligned - ((b - self._clamped(b)) @ self.components).reshape(self._n, 2)
        norm = float(np.linalg.norm(rest))
        if self.residual_max is not None and norm > self.residual_max:
            rec -= (1.0 - self.residual_max / norm) * rest
        if self.keep_eyes:
            _restore_local(rec, aligned, self._eyes)
        if self.eye_open_max is not None:
            _cap_eyes(rec, self._scheme, self._eyes, self.eye_open_max)
        n = ca * ca + sa * sa
        inv = np.array([[ca, sa], [-sa, ca]]) / n
        return (rec - self._mu) @ inv.T + mo


def _restore_local(rec: np.ndarray, before: np.ndarray, patches: tuple) -> None:
    """Put each eye contour of ``before`` (P, 2) onto ``rec``'s (P, 2) corners, in place
    (``patches``: :func:`eye_patches`): the similarity taking the eye's two corners in
    ``before`` to those in ``rec`` (complex arithmetic: z -> a + k z) moves its contour."""
    for idx, c0, c1 in patches:
        s0, s1, d0, d1 = (complex(*p) for p in (before[c0], before[c1], rec[c0], rec[c1]))
        if s1 == s0:
            continue
        k = (d1 - d0) / (s1 - s0)
        z = (before[idx, 0] - s0.real + 1j * (before[idx, 1] - s0.imag)) * k + d0
        rec[idx, 0], rec[idx, 1] = z.real, z.imag


def _cap_eyes(rec: np.ndarray, scheme: LandmarkScheme, patches: tuple, cap: np.ndarray) -> None:
    """Squash each eye of ``rec`` (P, 2) whose opening (:func:`eye_openings`) exceeds ``cap``
    (2,) towards the line through its corners until it equals the cap, in place: the eye's
    points (contour and iris, ``patches``: :func:`eye_patches`) keep their position along
    the corner line and their distance across it is scaled by cap / opening (an affine
    squash: no triangle of the eye turns over)."""
    for (idx, c0, c1), opening, m in zip(patches, eye_openings(rec, scheme), cap, strict=True):
        if opening <= m:
            continue
        axis = rec[c1] - rec[c0]
        normal = np.array([-axis[1], axis[0]]) / np.hypot(*axis)
        h = (rec[idx] - rec[c0]) @ normal
        rec[idx] -= np.outer((1.0 - m / opening) * h, normal)


__all__ = ["RETARGET_SCHEMES", "ShapeSpace", "eye_patches", "retarget_scheme"]
