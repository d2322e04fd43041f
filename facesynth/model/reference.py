"""The reference frame: the mean shape at a fixed pixel scale, its triangulation, its
mask, and the fixed per-pixel triangle index and barycentric coordinates.

Coordinates are (x, y) with integer values at pixel centres (OpenCV's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay

from facesynth.errors import FacesynthError
from facesynth.landmarks import facing_pairs, folded_triangles, triangle_areas


@dataclass
class ReferenceFrame:
    """Attributes
    ----------
    points : np.ndarray
        float32 (P, 2): reference landmarks, (x, y) pixels in the reference image (P from
        the landmark scheme: 68, 478).
    size : tuple of int
        (H, W) of the reference image.
    triangles : np.ndarray
        int64 (T, 3): the scheme's fixed triangulation less the triangles folded on the
        mean shape, or the Delaunay triangulation of ``points`` (counter-clockwise in image
        axes). Points in no triangle (MediaPipe's irises) do not move the warp.
    """

    points: np.ndarray
    size: tuple[int, int]
    triangles: np.ndarray

    @classmethod
    def from_mean_shape(cls, mean_shape: np.ndarray, width: int = 128, margin: float = 0.1,
                        triangles: np.ndarray | None = None) -> "ReferenceFrame":
        """Scale a (P, 2) mean shape so that its landmark bounding box is ``width`` pixels
        wide, add ``margin`` (fraction of the width) on every side, and triangulate it:
        with Delaunay, or with the fixed ``triangles`` (T, 3) of the landmark scheme. A fixed
        triangle folded on this mean (it overlaps its neighbours there) is kept, turned
        counter-clockwise and moved to the end of the list: reference pixels then belong to
        the unfolded triangles first (:func:`locate` takes the first), and a frame where it
        unfolds still covers it (dropping it left holes there)."""
        if width < 16:
            raise FacesynthError(f"reference width must be >= 16 px, got {width}")
        pts = np.asarray(mean_shape, np.float64)
        lo, hi = pts.min(0), pts.max(0)
        scale = (width - 1) / (hi[0] - lo[0])
        pad = margin * width
        pts = (pts - lo) * scale + pad
        size = (int(np.ceil(pts[:, 1].max() + pad)) + 1, int(np.ceil(pts[:, 0].max() + pad)) + 1)
        if triangles is None:
            tri = orient_ccw(pts, Delaunay(pts).simplices.astype(np.int64))
        else:
            tri = np.asarray(triangles, np.int64)
            folded = folded_triangles(pts, tri)
            if folded.all():
                raise FacesynthError("every triangle of the fixed triangulation is folded on the mean shape")
            tri = np.concatenate([tri[~folded], orient_ccw(pts, tri[folded])])
        return cls(pts.astype(np.float32), size, tri)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def rasterise(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel triangle index and barycentric coordinates of the reference image.

        Returns
        -------
        tri_index : np.ndarray
            int64 (H, W); -1 outside the triangulated face region.
        bary : np.ndarray
            float32 (H, W, 3); weights of the triangle's three vertices (0 outside).
        """
        cached = self.__dict__.get("_raster")
        if cached is None:
            h, w = self.size
            ys, xs = np.mgrid[0:h, 0:w]
            pix = np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64)
            tri_index, bary = locate(pix, self.points.astype(np.float64), self.triangles)
            cached = (tri_index.reshape(h, w), bary.reshape(h, w, 3).astype(np.float32))
            self.__dict__["_raster"] = cached
        return cached

    def mask(self) -> np.ndarray:
        """bool (H, W): pixels covered by the triangulation."""
        return self.rasterise()[0] >= 0


AUTO_WIDTH = (128, 256, 16)
"""``reference_width=auto``: the range (lowest, highest) and the step (px) of the width. 128 is
the fixed default; 256 holds 4x its pixels and was the widest measured (training peak memory
2.7-3.0 GB, the exported model 326-395 frames/s at batch 1 on one thread: docs/sadm.md,
"Reference frame size")."""


def reference_width(setting, landmarks: np.ndarray) -> int:
    """The reference frame's width (px) for the ``model.reference_width`` setting: an int as
    given, or ``"auto"``: the training faces' width in the video, the median over frames of
    the width of the landmarks' bounding box ((N, P, 2) frame pixels), rounded up to a
    multiple of 16 and kept within :data:`AUTO_WIDTH`'s range, so that the reference frame
    samples the face at about the video's own resolution rather than upscaling it."""
    if isinstance(setting, str):
        if setting != "auto":
            raise FacesynthError(f"model.reference_width must be a number of pixels or 'auto', got {setting!r}")
        lo, hi, step = AUTO_WIDTH
        width = float(np.median(np.ptp(np.asarray(landmarks, np.float64)[..., 0], axis=-1)))
        return int(min(max(int(np.ceil(width / step)) * step, lo), hi))
    return int(setting)


def lip_gap(shapes: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Mouth opening of (..., P, 2) shapes: the mean distance between facing inner-lip points
    over the distance between the inner mouth corners -> (...,). ``ring``: the scheme's
    ``inner_lips`` (L points, a closed ring: corner, upper lip, the other corner at L / 2,
    lower lip), so point k faces point L - k."""
    ring = np.asarray(ring, np.int64)
    n = len(ring)
    upper, lower = facing_pairs(ring)
    s = np.asarray(shapes, np.float64)
    width = np.linalg.norm(s[..., ring[0], :] - s[..., ring[n // 2], :], axis=-1)
    return np.linalg.norm(s[..., upper, :] - s[..., lower, :], axis=-1).mean(-1) / width


OPEN_MOUTH_STEPS = (1.0, 0.8, 0.6, 0.4, 0.2)  # fractions of the opening tried, widest first


def open_mouth(mean: np.ndarray, shapes: np.ndarray, ring: np.ndarray, quantile: float,
               triangles: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The mean shape (P, 2) with its mouth opened to the ``quantile`` of the (N, P, 2)
    aligned training shapes' :func:`lip_gap`, along the shapes' linear regression on the gap
    (the way this face opens its mouth: jaw, lips and cheeks together). Unchanged when its
    gap is already that wide. A reference frame whose lips touch gives the triangles that
    close a fixed mesh's mouth no pixels, so the appearance model never holds the inside of
    the mouth. With ``triangles`` (T, 3), the opening is cut back (:data:`OPEN_MOUTH_STEPS`)
    until it folds no triangle that the mean does not fold: a triangle dropped from the
    reference frame would leave a hole wherever a frame gives it area. Returns the shape and
    what was done (for the model's meta)."""
    g = lip_gap(shapes, ring)
    want, have = float(np.quantile(g, quantile)), float(lip_gap(mean, ring))
    info = {"quantile": float(quantile), "gap_mean_shape": have, "gap_target": want}
    dg = g - g.mean()
    if want <= have or float(dg @ dg) == 0.0:
        return mean, {**info, "opened": False}
    slope = np.tensordot(dg, np.asarray(shapes, np.float64) - mean, 1) / float(dg @ dg)  # (P, 2) per unit of gap
    mean = np.asarray(mean, np.float64)
    out = mean
    for _ in range(3):  # the gap is not exactly linear along the slope: a few secant steps
        out = out + (want - lip_gap(out, ring)) * slope
    if triangles is None:
        return out, {**info, "opened": True, "gap_reference": float(lip_gap(out, ring)), "fraction": 1.0}
    tri = np.asarray(triangles, np.int64)
    base = folded_triangles(mean, tri)
    for frac in OPEN_MOUTH_STEPS:
        cand = mean + frac * (out - mean)
        if not (folded_triangles(cand, tri) & ~base).any():
            return cand, {**info, "opened": True, "gap_reference": float(lip_gap(cand, ring)), "fraction": frac}
    return mean, {**info, "opened": False, "fraction": 0.0}


AREA_STEPS = (1.0, 0.8, 0.6, 0.4, 0.2)  # fractions of the spreading tried, whole first
AREA_STRETCH = 2.0  # how far a frame may stretch a reference triangle (area ratio) before it is spread
AREA_KEEP = 1.0  # the share of its own area every other triangle keeps while the slivers spread


def spread_triangles(shape: np.ndarray, shapes: np.ndarray, triangles: np.ndarray, quantile: float,
                     stretch: float = AREA_STRETCH, stiffness: float = 1e-3) -> tuple[np.ndarray, dict]:
    """The reference ``shape`` (P, 2) moved as little as it takes for every triangle of a fixed
    triangulation (T, 3) to hold at least 1 / ``stretch`` of the ``quantile`` of its share of the
    face's area over the (N, P, 2) aligned training shapes: no training frame up to that
    quantile stretches it more than ``stretch`` times in area. A mean shape averages a band that
    most frames fold or squash (lp_d6's MediaPipe points 17-18 under the lower lip: 0.015 eye
    widths on the mean, 0.09 at the 95th percentile, 0.12 on its neutral) into a sliver of a
    pixel, and a face rendered where that band is wide stretches those rows into streaks.
    Solved by L-BFGS on the squared relative shortfalls (every other triangle's below
    :data:`AREA_KEEP` of its own area: none pays for a sliver with its own pixels) plus
    ``stiffness`` times the squared displacement (in units of the face's area); then cut back
    (:data:`AREA_STEPS`) until it folds no triangle the shape does not fold. Returns the shape
    and what was done (for the model's meta)."""
    from scipy.optimize import minimize

    tri = np.asarray(triangles, np.int64)
    x0 = np.asarray(shape, np.float64)
    own = triangle_areas(x0, tri)
    live = own > 0  # triangles folded on the shape itself keep their place (ReferenceFrame puts them last)
    area = triangle_areas(shapes, tri)
    share = area / np.abs(area).sum(-1, keepdims=True)
    total = float(own[live].sum())
    want = np.quantile(share, quantile, axis=0) * total / stretch  # (T,) target areas on this shape's scale
    short = live & (want > own)
    info = {"quantile": float(quantile), "short_triangles": int(short.sum()),
            "largest_shortfall": float((want[short] / own[short]).max()) if short.any() else 1.0}
    if not short.any():
        return x0, {**info, "spread": False}
    # every other live triangle keeps its area (else the spread only moves the stretch to a neighbour)
    target = np.where(short, want, AREA_KEEP * own)
    t, w, scale = tri[live], target[live], stiffness / total

    def f(v):
        x = v.reshape(x0.shape)
        a, b, c = x[t[:, 0]], x[t[:, 1]], x[t[:, 2]]
        u, s = b - a, c - a
        gap = np.maximum(w - 0.5 * (u[:, 0] * s[:, 1] - u[:, 1] * s[:, 0]), 0.0) / w
        d = x - x0
        g = np.zeros_like(x)
        coef = (-2.0 * gap / w)[:, None]  # d(gap^2)/d(area)
        gb, gc = 0.5 * np.stack([s[:, 1], -s[:, 0]], 1), 0.5 * np.stack([-u[:, 1], u[:, 0]], 1)
        np.add.at(g, t[:, 1], coef * gb)
        np.add.at(g, t[:, 2], coef * gc)
        np.add.at(g, t[:, 0], -coef * (gb + gc))
        return float((gap ** 2).sum() + scale * (d ** 2).sum()), (g + 2.0 * scale * d).ravel()

    out = minimize(f, x0.ravel(), jac=True, method="L-BFGS-B", options={"maxiter": 500}).x.reshape(x0.shape)
    base = folded_triangles(x0, tri)
    for frac in AREA_STEPS:
        cand = x0 + frac * (out - x0)
        if not (folded_triangles(cand, tri) & ~base).any():
            got = triangle_areas(cand, tri)
            return cand, {**info, "spread": True, "fraction": frac,
                          "largest_shortfall_after": float(max((want[short] / got[short]).max(), 1.0)),
                          "largest_move": float(np.abs(cand - x0).max() / np.sqrt(total))}
    return x0, {**info, "spread": False, "fraction": 0.0}


def subset_triangulation(points: np.ndarray, subset: np.ndarray) -> np.ndarray:
    """int64 (T, 3) counter-clockwise Delaunay triangles of ``points[subset]`` ((P, 2) points,
    ``subset`` indices into them), as indices into ``points``: the other points are no vertices."""
    subset = np.asarray(subset, np.int64)
    return subset[orient_ccw(points[subset], Delaunay(points[subset]).simplices.astype(np.int64))]


def orient_ccw(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reorder triangle vertices so that every triangle has positive signed area."""
    p = points[triangles]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    out = triangles.copy()
    out[area < 0] = out[area < 0][:, [0, 2, 1]]
    return out


def barycentric(pix: np.ndarray, tri_pts: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of (P, 2) points in each of (T, 3, 2) triangles -> (P, T, 3)."""
    v0, v1, v2 = tri_pts[:, 0], tri_pts[:, 1], tri_pts[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    d = pix[:, None, :] - v0[None]
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero-area triangle: inf / NaN, contains no point
        l1 = (d[..., 0] * e2[:, 1] - d[..., 1] * e2[:, 0]) / det
        l2 = (e1[:, 0] * d[..., 1] - e1[:, 1] * d[..., 0]) / det
    return np.stack([1 - l1 - l2, l1, l2], -1)


def locate(pix: np.ndarray, points: np.ndarray, triangles: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """First triangle containing each point, and its barycentrics (brute force, for fixed geometry).

    Parameters
    ----------
    pix : (P, 2) points; points : (68, 2) vertices; triangles : (T, 3) indices.

    Returns
    -------
    tri_index : int64 (P,), -1 where no triangle contains the point; bary : (P, 3).
    """
    out_t = np.full(len(pix), -1, np.int64)
    out_b = np.zeros((len(pix), 3))
    for start in range(0, len(pix), 8192):
        b = barycentric(pix[start : start + 8192], points[triangles])
        inside = (b >= -eps).all(-1)
        has = inside.any(1)
        first = inside.argmax(1)
        idx = np.arange(start, start + len(b))
        out_t[idx[has]] = first[has]
        out_b[idx[has]] = b[np.flatnonzero(has), first[has]]
    return out_t, out_b
