"""The whole avatar frame follows the head: a landmark-driven warp of the avatar's neutral
frame (numpy + OpenCV, no torch), into which the synthesised face is then composited.

Control points, all placed on the avatar's neutral face (its iBUG-68 view; :func:`head_points`):

* the face's 68 landmarks, which go where the avatar's landmarks of the frame are;
* a ring round the head (ears, over the hair), neck points below the jaw and an outer
  ring, in the face's own units (origin between the eyes, unit the outer-eye-corner
  distance, the face's axes); the rings' size is the warp's ``ring_scale`` times
  ``HEAD_AXES``, per avatar (a slick bun and a mane differ: :mod:`facesynth.onnx.headmotion`
  chooses it on the avatar's own video);
* anchors along the frame border.

Each point ``p`` but the landmarks goes to ``p + a (S(p) - p) + b d``: ``S`` is the
similarity fitted from the neutral's eye corners, top of the nose bridge and top jaw points
(by the ears) to the frame's, and ``d`` takes out the parallax of a head turn: turning (yaw)
or nodding (pitch) shifts the face's front, where the landmarks are, further than the head's
outline, so ``d`` is minus the nose tip's offset from where ``S`` puts the neutral's (the
nose tip relative to the outer eye corners' midpoint; 0 under any similarity of the face, so
a rigid 2D motion of the face moves the whole head exactly). The shares ``(a, b)`` are the
warp's ``motion``: by default ``w`` and ``PARALLAX w`` (:meth:`FrameWarp.prior`), where
``w`` is 1 on the head's ring, falls off linearly outside it, more so below the chin, and is
0 at the shoulders and on the frame's border away from the head (:func:`motion_weight`); an
exported model carries its own, learned from the avatar's video
(:mod:`facesynth.onnx.headmotion`).

Anchors on the left, right and bottom sides only slide along them (the bottom corners stay):
where a chin or shoulder reaches the bottom, the edge follows the head along it, never
across it: an edge moved inward shows what lies beyond it (streaks, or a mirrored body). A chin that comes
closer to the bottom than ``CHIN_MARGIN`` face units (or than it is on the neutral, if
closer) pushes the bottom side's anchors out below the frame by as much, where it would
otherwise pass them, or the jaw's slope would, and fold the band between (dark specks and a
jagged jaw line at the frame's bottom). Anchors on the top
side also move down with the head: hair cut by the frame's top then continues above it as
the top rows mirrored (held on the top edge instead, the hair was pulled into a peak
there), and the ring's points above the frame are kept, so that the hair there moves with
the head. Ring points on the border band or outside the frame elsewhere are dropped, on the
neutral: the triangulation is fixed per avatar. A still guard ring ``GUARD`` times the
frame's size outside it closes the triangulation round the frame, so that every pixel lies
in a triangle however the anchors move (the band above top anchors that moved down stretches
from them to the guards, where it would otherwise keep its own pixels: a tear along the
frame's top).

Two interpolants of the control points' motion (``method``):

* ``"affine"``: piecewise affine on the Delaunay triangulation of the control points in
  the neutral frame, evaluated exactly at the nodes of a grid of about ``GRID_STEP``
  pixels (:func:`grid_nodes`, the frame's first and last rows and columns included) and
  bilinear between them: each node takes the affine map (output -> neutral pixels) of the
  warped triangle that contains it; a node that no warped triangle contains (a fold's
  gap), or that two contain (where a fold overlaps), keeps its own position. Never a hole:
  every pixel reads some map. The map is continuous, so between nodes the bilinear
  interpolation departs from the exact map only in cells crossed by a triangle edge where
  the map's slope jumps (the jaw, the head's ring), by up to a quarter cell times the jump:
  a staircase of the grid's step along the outline (:mod:`facesynth.eval.jaggedness`). A
  per-pixel triangle search would cost the talking-head graph several times its budget.
* ``"tps"``: a thin-plate spline from the warped control points back to the neutral ones
  (so the inverse map is evaluated directly), on a grid of one node per ``TPS_STEP``
  pixels, bilinearly upsampled; smooth, but its bending can overshoot between control
  points that move differently (eyelids under still brows).

The inverse map is sampled with ``cv2.remap`` (bilinear). Beyond the frame's edge the frame is
mirrored (``BORDER_REFLECT_101``; for "affine" the grid nodes' maps are reflected into the frame
before the upsampling): a replicated edge showed as stripes above a head that moved down.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import Delaunay

from facesynth.errors import FacesynthError
from facesynth.faps import face_axes
from facesynth.geometry import apply_affine, mirror, similarity_fit, thin_plate
from facesynth.landmarks import ibug68_view, inter_ocular

METHODS = ("affine", "tps")
# (x, down) in face units (origin between the eyes, unit the outer-eye-corner distance)
HEAD_CENTRE, HEAD_AXES = (0.0, 0.1), (1.15, 1.5)  # an ellipse round the head: ears, hair
HEAD_RING_DEG = np.arange(160.0, 381.0, 20.0)  # its points from one ear over the top of the head to the other
RING_SCALE = 1.0  # the ellipse's size, times HEAD_AXES, where the avatar has not chosen its own
RING_SCALE_MAX = 10.0  # a ring_scale read from metadata or given must be below it
OUTER_RING_DEG = np.arange(0.0, 360.0, 30.0)
OUTER_SCALE = 1.6  # a ring at 1.6 x the head's ellipse, at part of its motion
FALLOFF = 2.2  # the head's motion falls off linearly from its ellipse (1) to 2.2 x it (0)
# the head's outline moves by the face's similarity less this times the nose tip's parallax
# (module docstring; docs/reenact.md "The head's outline turns less than the face")
PARALLAX = 1.0
NOSE_TIP, EYE_CORNERS = 30, (36, 45)
CHIN, SHOULDERS = 1.5, 3.0  # below the chin it falls off further, to nothing at the shoulders
NECK = ((-0.6, 1.6), (0.6, 1.6), (0.0, 2.05))
CHIN_MARGIN = 0.25  # the bottom anchors keep the lowest landmark this far (face units) above them
BORDER_STEPS = 8  # anchors per frame side (corners included)
INSIDE = 0.02  # ring points closer to the frame's border than this share of its size are dropped,
OUTSIDE = 0.25  # and so are those outside it, but for those above it by less than this share
GUARD = 0.3  # a still guard ring this share of the frame's size outside it (module docstring)
# the head's motion: the similarity fitted on the eye corners, the top of the nose bridge and
# the jaw's top points by the ears (the nose tip and the lower jaw turn ahead of the skull)
HEAD_POINTS = [0, 1, 15, 16, 27, 36, 39, 42, 45]
TPS_STEP = 8
GRID_STEP = 4  # the affine warp's grid (module docstring): at 8 px the outline showed a staircase


def face_frame(face68: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Origin (between the eyes), axes (2, 2) rows (x, down) and unit (outer-eye-corner
    distance, pixels) of a (68, 2) face."""
    f = np.asarray(face68, np.float64)
    return f[36:48].mean(0), face_axes(f), float(inter_ocular(f))


def nose_offset(face68: np.ndarray) -> np.ndarray:
    """(2,) the nose tip's offset from the outer eye corners' midpoint of a (68, 2) face, in
    pixels: it grows with a head turn or nod (module docstring, ``PARALLAX``)."""
    f = np.asarray(face68, np.float64)
    return f[NOSE_TIP] - 0.5 * (f[EYE_CORNERS[0]] + f[EYE_CORNERS[1]])


def motion_weight(face_xy: np.ndarray, ring_scale: float = RING_SCALE) -> np.ndarray:
    """(K,) share of the head's motion that points at (K, 2) face-unit (x, down) positions
    follow: 1 on and inside the head's ellipse (its axes ``ring_scale`` x ``HEAD_AXES``),
    falling off linearly to 0 at ``FALLOFF`` times it, and below the chin further, to 0 at
    the shoulders."""
    xy = np.asarray(face_xy, np.float64)
    ax, ay = ring_scale * HEAD_AXES[0], ring_scale * HEAD_AXES[1]
    r = np.hypot(xy[:, 0] / ax, (xy[:, 1] - HEAD_CENTRE[1]) / ay)
    w = np.clip(1.0 - (r - 1.0) / (FALLOFF - 1.0), 0.0, 1.0)
    return w * np.clip(1.0 - (xy[:, 1] - CHIN) / (SHOULDERS - CHIN), 0.0, 1.0)


def ellipse_points(degrees: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(N, 2) face-unit (x, down) points of the head's ellipse, ``scale`` times ``HEAD_AXES``
    round ``HEAD_CENTRE``, at ``degrees`` (N,) (0 to the face's right, 90 down)."""
    t = np.deg2rad(degrees)
    return np.stack([scale * HEAD_AXES[0] * np.cos(t), HEAD_CENTRE[1] + scale * HEAD_AXES[1] * np.sin(t)], 1)


def head_points(neutral68: np.ndarray, size: tuple[int, int], ring_scale: float = RING_SCALE) -> tuple[np.ndarray, np.ndarray]:
    """Control points besides the face's landmarks, on a (68, 2) neutral face in a frame of
    ``size`` (W, H), the head's ellipse ``ring_scale`` times its default size: points (K, 2)
    float64 and the share of the head's motion each follows (K,) (:func:`motion_weight`;
    module docstring)."""
    w, h = size
    o, axes, unit = face_frame(neutral68)
    rings = [ellipse_points(HEAD_RING_DEG, ring_scale), np.asarray(NECK),
             ellipse_points(OUTER_RING_DEG, OUTER_SCALE * ring_scale)]
    pts = o + unit * np.concatenate(rings) @ axes
    out, near = OUTSIDE * max(w, h), INSIDE * max(w, h)
    top = np.array([w - 1, h - 1])
    inner = np.all((pts > near) & (pts < top - near), 1)
    # above the frame (hair the top edge cuts): kept, the top anchors move down with the head
    above = (pts[:, 1] < -near) & (pts[:, 1] > -out) & (pts[:, 0] > near) & (pts[:, 0] < w - 1 - near)
    pts = pts[inner | above]
    bx = np.linspace(0, w - 1, BORDER_STEPS + 1)
    by = np.linspace(0, h - 1, BORDER_STEPS + 1)
    border = np.concatenate([np.stack([bx, np.zeros_like(bx)], 1), np.stack([bx, np.full_like(bx, h - 1)], 1),
                             np.stack([np.zeros_like(by[1:-1]), by[1:-1]], 1),
                             np.stack([np.full_like(by[1:-1], w - 1), by[1:-1]], 1)])
    g = GUARD * max(w, h)  # still points round the frame: every pixel lies in some triangle, however the anchors move
    gx, gy = np.linspace(-g, w - 1 + g, BORDER_STEPS + 1), np.linspace(-g, h - 1 + g, BORDER_STEPS + 1)
    guard = np.concatenate([np.stack([gx, np.full_like(gx, -g)], 1), np.stack([gx, np.full_like(gx, h - 1 + g)], 1),
                            np.stack([np.full_like(gy[1:-1], -g), gy[1:-1]], 1),
                            np.stack([np.full_like(gy[1:-1], w - 1 + g), gy[1:-1]], 1)])
    weights = np.concatenate([motion_weight((np.concatenate([pts, border]) - o) @ axes.T / unit, ring_scale),
                              np.zeros(len(guard))])
    return np.concatenate([pts, border, guard]), weights


def head_region(face68: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """bool (H, W): the face's landmark hull grown to take in hair and neck (the convex hull
    of the landmarks, the head ring and the neck points of :func:`head_points` on this face,
    clipped to the frame)."""
    w, h = size
    o, axes, unit = face_frame(face68)
    pts = np.concatenate([np.asarray(face68, np.float64), o + unit * np.concatenate([ellipse_points(HEAD_RING_DEG), NECK]) @ axes])
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(pts * 16).astype(np.int32)), 1, cv2.LINE_8, 4)
    return mask.astype(bool)


class FrameWarp:
    """Warp an avatar's neutral frame so that its face lands on given landmarks, the head
    around it following, the frame's border still.

    frame : uint8 (H, W, 3) the avatar's neutral frame; neutral : (P, 2) its landmarks
    (any registered scheme; the iBUG-68 view is used); method : "affine" (default) or "tps";
    motion : float (K - 68, 2) per control point besides the landmarks, the share of the
    head's motion ``S`` and of the parallax term ``d`` it follows (default :meth:`prior`,
    ``w`` and ``PARALLAX w``; :mod:`facesynth.onnx.headmotion` learns them from the
    avatar's video); ring_scale : the head's ellipse, ring and falloff, this times its
    default size (:func:`head_points`); grid_step : the "affine" grid's node spacing, px (1: exact).

    ``__call__(landmarks)``: (P, 2) avatar landmarks in the frame -> uint8 (H, W, 3).
    """

    def __init__(self, frame: np.ndarray, neutral: np.ndarray, method: str = "affine",
                 motion: np.ndarray | None = None, ring_scale: float = RING_SCALE, grid_step: int = GRID_STEP):
        if method not in METHODS:
            raise FacesynthError(f"full-frame warp: method must be one of {METHODS}, got {method!r}")
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.dtype != np.uint8:
            raise FacesynthError(f"full-frame warp: expected a uint8 (H, W, 3) frame, got {frame.dtype} {frame.shape}")
        self.frame, self.method = frame, method
        h, w = frame.shape[:2]
        self.size = (w, h)
        self.n_points = int(np.asarray(neutral).shape[-2])  # of the landmarks' scheme (P)
        self.neutral68 = ibug68_view(neutral)
        if not np.isfinite(self.neutral68).all():
            raise FacesynthError("full-frame warp: the avatar's neutral landmarks are not finite")
        self.ring_scale = checked_ring_scale(ring_scale)
        extra, self.weights = head_points(self.neutral68, self.size, self.ring_scale)
        self.src = np.concatenate([self.neutral68, extra])  # (K, 2) control points in the neutral frame
        self.n_face = len(self.neutral68)
        # (K - 68, 2) the axes a point moves along: a side's anchor keeps the coordinate on it
        held = np.stack([(extra[:, 0] == 0.0) | (extra[:, 0] == w - 1.0), extra[:, 1] == h - 1.0], 1)
        self.free = ~held
        # (K - 68,) the points that follow the head in full: its ring and inside it (w = 1 up to rounding)
        self.on_ring = self.weights >= 1.0 - 1e-6
        self.motion = self.prior() if motion is None else _checked_motion(motion, len(extra))
        g = GUARD * max(w, h)
        self.guard = (extra[:, 0] <= -g) | (extra[:, 0] >= w - 1 + g) | (extra[:, 1] <= -g) | (extra[:, 1] >= h - 1 + g)
        self._ring = ~(held.any(1) | (extra[:, 1] == 0.0) | self.guard)
        self.bottom = held[:, 1]  # (K - 68,) the bottom side's anchors, corners too
        # how far above the bottom anchors the lowest landmark stays (px; module docstring)
        self.chin_margin = float(min(h - 1.0 - self.neutral68[:, 1].max(), CHIN_MARGIN * face_frame(self.neutral68)[2]))
        self.triangles = Delaunay(self.src).simplices.astype(np.int64)
        if isinstance(grid_step, bool) or not isinstance(grid_step, (int, np.integer)) or grid_step < 1:
            raise FacesynthError(f"full-frame warp: grid_step must be a whole number of pixels >= 1, got {grid_step!r}")
        self.nodes = grid_nodes(w, int(grid_step)), grid_nodes(h, int(grid_step))  # (x, y) of the affine warp's grid
        # the anchors on the frame's border are pushed a thousandth of a node spacing out when
        # nodes are located (not for the maps): the nodes on the border then lie strictly
        # inside the frame's triangles, never on a tie (the graph's scanline coverage is
        # half-open on the right and bottom, and an anchor the head leaves still sits on a
        # node of the top or left edge); in node units, (K, 2)
        push = np.zeros_like(self.src)
        push[self.n_face:, 0] = np.where(extra[:, 0] == w - 1, 1e-3, np.where(extra[:, 0] == 0.0, -1e-3, 0.0))
        push[self.n_face:, 1] = np.where(extra[:, 1] == h - 1, 1e-3, np.where(extra[:, 1] == 0.0, -1e-3, 0.0))
        self.locate_push = push
        self._up = interpolation_weights(w, len(self.nodes[0])), interpolation_weights(h, len(self.nodes[1]))
        self._grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), -1)

    def control_points(self, landmarks: np.ndarray) -> np.ndarray:
        """float64 (K, 2): where the control points go for (P, 2) avatar landmarks."""
        face = ibug68_view(landmarks)
        move, d = motion_features(self, face)
        share, parallax = self.shares()
        moved = self.src[self.n_face:] + share * move + parallax * d
        # ring points stay strictly inside the held sides (past them they would fold over the anchors)
        r = self._ring
        moved[r, 0] = np.clip(moved[r, 0], 1.0, self.size[0] - 2.0)
        moved[r, 1] = np.minimum(moved[r, 1], self.size[1] - 2.0)
        moved[self.bottom, 1] += max(0.0, face[:, 1].max() + self.chin_margin - (self.size[1] - 1.0))
        return np.concatenate([face, moved])

    def prior(self) -> np.ndarray:
        """float64 (K - 68, 2) the geometric motion coefficients: ``w`` (:func:`motion_weight`)
        of the head's motion and ``PARALLAX w`` of the parallax term."""
        return np.stack([self.weights, PARALLAX * self.weights], 1)

    def shares(self) -> tuple[np.ndarray, np.ndarray]:
        """(K - 68, 2) each, per point and axis: the share of the head's motion and of the
        parallax term it follows (``motion`` on the axes it is free to move along)."""
        return self.motion[:, :1] * self.free, self.motion[:, 1:] * self.free

    def folds(self, landmarks: np.ndarray, outside_face: bool = False) -> int:
        """Number of triangles whose orientation the warp turns (0: no fold); ``outside_face``:
        only those with a vertex besides the face's landmarks (a fold among the landmarks
        alone, e.g. of the lips, lies under the composited face)."""
        dst = self.control_points(landmarks)
        flip = np.sign(_signed_area(self.src, self.triangles)) != np.sign(_signed_area(dst, self.triangles))
        if outside_face:
            flip &= (self.triangles >= self.n_face).any(1)
        return int(flip.sum())

    def maps(self, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """float32 (H, W) x and y maps: output pixel -> neutral-frame pixel (for ``cv2.remap``)."""
        dst = self.control_points(landmarks)
        return self._affine_maps(dst) if self.method == "affine" else self._tps_maps(dst)

    def __call__(self, landmarks: np.ndarray) -> np.ndarray:
        mx, my = self.maps(landmarks)
        return cv2.remap(self.frame, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)

    def _affine_maps(self, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        (kx, fx), (ky, fy) = self._up
        m = mirror(self.node_maps(dst), np.array([self.size[0] - 1.0, self.size[1] - 1.0])[:, None, None])
        m = m[:, :, kx] * (1.0 - fx) + m[:, :, kx + 1] * fx  # along x: (2, Hn, W)
        m = m[:, ky] * (1.0 - fy)[:, None] + m[:, ky + 1] * fy[:, None]  # along y: (2, H, W)
        return np.ascontiguousarray(m[0], np.float32), np.ascontiguousarray(m[1], np.float32)

    def node_maps(self, dst: np.ndarray) -> np.ndarray:
        """float64 (2, Hn, Wn): the neutral-frame pixel (x, y) each grid node reads, for the
        control points at ``dst`` (K, 2) (:meth:`control_points`)."""
        tri = self.triangles
        d = dst[tri]  # (T, 3, 2)
        a = np.concatenate([d, np.ones((len(tri), 3, 1))], 2)  # (T, 3, 3) rows [x y 1]
        det = np.linalg.det(a)
        ok = np.abs(det) > 1e-9
        m = np.zeros((len(tri), 2, 3))
        # rows [x y 1] @ M^T = src: M^T = A^-1 src
        m[ok] = np.linalg.solve(a[ok], self.src[tri[ok]]).transpose(0, 2, 1)
        nx, ny = self.nodes
        gx, gy = np.meshgrid(nx, ny)
        spacing = np.array([nx[1] - nx[0], ny[1] - ny[0]])
        loc = (dst + self.locate_push * spacing)[tri]  # where the nodes are located
        # every (triangle, node) pair whose node lies in the triangle's bounding box, triangle-major
        ts = np.flatnonzero(ok)
        lo, hi = loc[ts].min(1) - 1e-6, loc[ts].max(1) + 1e-6
        c0, c1 = np.searchsorted(nx, lo[:, 0]), np.searchsorted(nx, hi[:, 0], "right")
        r0, r1 = np.searchsorted(ny, lo[:, 1]), np.searchsorted(ny, hi[:, 1], "right")
        wide, tall = np.maximum(c1 - c0, 0), np.maximum(r1 - r0, 0)
        n_pairs = wide * tall
        t = np.repeat(ts, n_pairs)
        k = np.arange(int(n_pairs.sum())) - np.repeat(np.cumsum(n_pairs) - n_pairs, n_pairs)  # within each box
        w_t = np.repeat(wide, n_pairs)
        col, row = np.repeat(c0, n_pairs) + k % np.maximum(w_t, 1), np.repeat(r0, n_pairs) + k // np.maximum(w_t, 1)
        x, y = nx[col], ny[row]
        (x0, y0), (x1, y1), (x2, y2) = (loc[t, j].T for j in range(3))
        den = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        l0 = ((y1 - y2) * (x - x2) + (x2 - x1) * (y - y2)) / den
        l1 = ((y2 - y0) * (x - x2) + (x0 - x2) * (y - y2)) / den
        inside = np.minimum(np.minimum(l0, l1), 1.0 - l0 - l1)
        node = row * len(nx) + col
        # triangles holding the node strictly inside; the node's map is its most inside
        # triangle's, the first in triangle order on a tie (on a shared edge either triangle's
        # map gives the same point; where a fold leaves a sliver, the sliver does not take it)
        count = np.bincount(node[inside > 1e-9], minlength=gx.size).reshape(gx.shape)
        order = np.lexsort((t, -inside, node))
        first = order[np.r_[True, node[order][1:] != node[order][:-1]]]
        first = first[inside[first] > -1e-9]
        own = np.stack([gx, gy])  # (2, Hn, Wn): where no single triangle holds the node
        maps = own.reshape(2, -1).copy()
        maps[:, node[first]] = np.einsum("nij,jn->in", m[t[first]], np.stack([x[first], y[first], np.ones(len(first))]))
        return np.where(count < 2, maps.reshape(own.shape), own)  # a node no triangle took kept its own position

    def _tps_maps(self, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w, h = self.size
        gx = np.arange(0, w - 1 + TPS_STEP, TPS_STEP, dtype=np.float64)
        gy = np.arange(0, h - 1 + TPS_STEP, TPS_STEP, dtype=np.float64)
        nodes = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
        src = thin_plate(dst, self.src, nodes).reshape(len(gy), len(gx), 2)
        # node (i, j) sits at pixel (j, i) * step: bilinear between nodes
        out = cv2.remap(src.astype(np.float32), self._grid[..., 0] / TPS_STEP, self._grid[..., 1] / TPS_STEP,
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return np.ascontiguousarray(out[..., 0]), np.ascontiguousarray(out[..., 1])


def grid_nodes(n: int, step: int = GRID_STEP) -> np.ndarray:
    """float64 positions of the affine warp's grid nodes along a side of ``n`` pixels:
    ``ceil((n - 1) / step) + 1`` nodes evenly from 0 to n - 1."""
    return np.linspace(0.0, n - 1.0, int(np.ceil((n - 1) / step)) + 1)


def interpolation_weights(n: int, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of pixels 0..n-1 between ``nodes`` evenly spaced nodes from 0 to
    n - 1 (node k at k (n - 1) / (nodes - 1); the ``align_corners`` convention of ONNX's
    Resize): int (n,) left node k and float64 (n,) weight f of node k + 1 (1 - f of node k)."""
    pos = np.arange(n, dtype=np.float64) * (nodes - 1) / (n - 1)
    k = np.minimum(np.floor(pos).astype(int), nodes - 2)
    return k, pos - k


def checked_ring_scale(value, name: str = "full-frame warp: ring_scale") -> float:
    """``value`` as a float, or FacesynthError naming ``name`` unless it is a number in
    (0, ``RING_SCALE_MAX``)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise FacesynthError(f"{name} must be a number, got {value!r}") from exc
    if not 0.0 < v < RING_SCALE_MAX:
        raise FacesynthError(f"{name} must be a positive factor of the head's ellipse below {RING_SCALE_MAX:g}, got {v}")
    return v


def motion_features(fw: FrameWarp, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two motions a control point besides the landmarks follows a share of, for (P, 2)
    avatar landmarks: the head's motion ``S(p) - p`` (K - 68, 2) at each point and the
    parallax term ``d`` (2,), pixels (module docstring)."""
    face = ibug68_view(landmarks)
    s = similarity_fit(fw.neutral68[HEAD_POINTS], face[HEAD_POINTS])
    extra = fw.src[fw.n_face:]
    return apply_affine(extra, s) - extra, s[:, :2] @ nose_offset(fw.neutral68) - nose_offset(face)


def _checked_motion(motion, n: int) -> np.ndarray:
    m = np.asarray(motion, np.float64)
    if m.shape != (n, 2) or not np.isfinite(m).all():
        raise FacesynthError(f"full-frame warp: frame_motion must be finite ({n}, 2) coefficients for this frame and "
                             f"neutral, got shape {m.shape}")
    return m


def _signed_area(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    p = points[tri]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]


__all__ = ["METHODS", "FrameWarp", "checked_ring_scale", "ellipse_points", "grid_nodes", "head_points", "head_region",
           "interpolation_weights", "motion_features", "nose_offset"]
