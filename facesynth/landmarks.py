"""Landmark schemes, defined once: how many points, which index is which part of the face,
and the rigid subsets the methods align on.

A landmark array is float32 (N, P, 2) of (x, y) pixel coordinates, 0-based, with P the
scheme's ``n_points``. Three schemes are registered in :data:`SCHEMES`:

* ``ibug68``: iBUG 300-W's 68-point markup (dlib's shape predictor, the ``.pts`` files of
  the 300-W data); the module-level constants (``JAW``, ``EYES``, ...) are its regions;
* ``mediapipe478``: MediaPipe Face Mesh with refined irises, 468 mesh points + 2 x 5 iris
  points (index tables in :mod:`facesynth.landmark_tables`), with the canonical mesh's
  fixed triangulation and an approximate mapping to ``ibug68`` (docs/landmarks.md).
* ``ibug68+iris``: dlib's 68 points followed by MediaPipe's 10 iris points (78 points; the
  face model uses the first 68, SADM's gaze path the irises).

Every module that needs to know which point is an eye corner or a lip takes the indices
from here::

    from facesynth.landmarks import IBUG68, EYES, INNER_LIPS
    lm[:, IBUG68.region("mouth")]
    get_scheme("mediapipe478").to_ibug68(lm478)   # (..., 478, 2) -> (..., 68, 2)

The rigid subsets differ on purpose: each method aligns on the points that its own input
never moves (see the docstring of each constant). A new scheme is one more
:class:`LandmarkScheme` registered in :data:`SCHEMES` (see docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

import cv2
import numpy as np

from facesynth import landmark_tables as mp
from facesynth.errors import FacesynthError

# ------------------------------------------------------------ iBUG 300-W, 68 points
JAW = tuple(range(0, 17))
RIGHT_BROW = tuple(range(17, 22))  # the subject's right (image left in a frontal view)
LEFT_BROW = tuple(range(22, 27))
BROWS = RIGHT_BROW + LEFT_BROW
NOSE_BRIDGE = tuple(range(27, 31))
NOSE_LOWER = tuple(range(31, 36))
NOSE = NOSE_BRIDGE + NOSE_LOWER
RIGHT_EYE = tuple(range(36, 42))
LEFT_EYE = tuple(range(42, 48))
EYES = RIGHT_EYE + LEFT_EYE
OUTER_LIPS = tuple(range(48, 60))
INNER_LIPS = tuple(range(60, 68))
MOUTH = OUTER_LIPS + INNER_LIPS

OUTER_EYE_CORNERS = (36, 45)  # their distance is the inter-ocular distance
INNER_EYE_CORNERS = (39, 42)
EYE_CORNERS = (36, 39, 42, 45)

RIGID_INNER = NOSE_BRIDGE + (31, 33, 35) + EYE_CORNERS
"""Nose bridge, nostrils, nose tip and eye corners: the frame-to-frame alignment of the 3D
transfer (head motion removed before expressions are measured) and the synthetic
subject's head pose."""

RIGID_NOSE_EYES = NOSE + EYE_CORNERS
"""The whole nose and the eye corners: SADM's ``landmarks_rigid`` features align on them."""

RIGID_FAP = NOSE_BRIDGE + (33,) + EYE_CORNERS
"""Points no MPEG-4 FAP moves: ERI fits the head pose (and places the forehead) on them."""

FAP_ANCHORS = (0, 16) + RIGID_FAP
"""Points held fixed when FAP displacements are spread over the other landmarks."""

POSE_POINTS = (0, 1, 15, 16) + NOSE + EYE_CORNERS
"""Points with stable 3D positions on a face mesh: head pose (DLT, EPnP) is fitted on them."""


@dataclass(frozen=True)
class LandmarkScheme:
    """A landmark markup: its name (recorded in every artifact), point count and named
    index sets (regions and rigid subsets).

    Attributes
    ----------
    name : str, e.g. "ibug68"
    n_points : int, P in (N, P, 2)
    regions : mapping name -> tuple of 0-based point indices
    description : str, one line for error messages and docs
    triangles : tuple of (a, b, c) index triples, or None
        A fixed triangulation of the face (counter-clockwise in image axes, x right and
        y down, on the canonical frontal face); None when it depends on the data
        (``ibug68``: the face model triangulates the mean shape with Delaunay).
    ibug68 : tuple of 68 index tuples, or None
        iBUG point i = mean of this scheme's points ``ibug68[i]``; None when no mapping is known.
    base : str or None
        A scheme whose points are this one's first points, unchanged (``ibug68+iris``:
        ``ibug68``, points 0-67); the face model of such a scheme is fitted on those alone.
    """

    name: str
    n_points: int
    regions: MappingProxyType = field(repr=False)
    description: str = ""
    triangles: tuple | None = field(default=None, repr=False)
    ibug68: tuple | None = field(default=None, repr=False)
    base: str | None = None

    def region(self, name: str) -> np.ndarray:
        """int64 indices of region ``name``; FacesynthError naming the known regions."""
        try:
            return np.asarray(self.regions[name], np.int64)
        except KeyError:
            raise FacesynthError(f"landmark scheme {self.name!r} has no region {name!r} "
                                 f"(it has {', '.join(sorted(self.regions))})") from None

    def check(self, landmarks: np.ndarray, where: str) -> None:
        """Raise FacesynthError unless ``landmarks`` is (..., n_points, 2); the message names
        the scheme the array seems to be in (by point count) and how to map it."""
        shape = np.shape(landmarks)
        if len(shape) < 2 or tuple(shape[-2:]) != (self.n_points, 2):
            raise FacesynthError(f"{where}: landmarks must have shape (..., {self.n_points}, 2) "
                                 f"({self.description}), got {tuple(shape)}{self.mismatch_hint(shape)}")

    def mismatch_hint(self, shape: tuple) -> str:
        """'; these look like <scheme> landmarks: map them with ...' for an array of another
        registered scheme's point count, else ''."""
        other = scheme_for_points(shape[-2]) if len(shape) >= 2 and shape[-1] == 2 else None
        if other is None or other is self:
            return ""
        if self is IBUG68 and other.ibug68 is not None:
            return (f"; these look like {other.name} landmarks: map them with "
                    f"get_scheme({other.name!r}).to_ibug68(...) or load_sequence(path, scheme='ibug68')")
        return f"; these look like {other.name} landmarks, which cannot be mapped to {self.name}"

    def base_scheme(self) -> "LandmarkScheme":
        """The scheme the face model of this one is fitted in: ``base`` if set, else itself
        (its points are ``landmarks[..., :base_scheme().n_points, :]``)."""
        return self if self.base is None else get_scheme(self.base)

    def triangulation(self) -> np.ndarray:
        """int64 (T, 3) fixed triangles; FacesynthError when the scheme has none."""
        if self.triangles is None:
            raise FacesynthError(f"landmark scheme {self.name!r} has no fixed triangulation "
                                 "(triangulate its mean shape instead)")
        return np.asarray(self.triangles, np.int64).reshape(-1, 3)

    def sparse_points(self) -> np.ndarray:
        """int64 sorted indices of a sparse warp's vertices: the points the iBUG-68 mapping reads,
        plus the eye and lip contours (``model.warp_points=sparse``); every point for ibug68."""
        if self is IBUG68:
            return np.arange(self.n_points)
        idx = set(np.flatnonzero(self.ibug68_matrix().any(0)).tolist())
        for region in ("eyes", "mouth"):
            idx.update(int(i) for i in self.region(region))
        return np.array(sorted(idx), np.int64)

    def ibug68_matrix(self) -> np.ndarray:
        """float64 (68, n_points) averaging matrix: ibug = M @ points (rows sum to 1)."""
        if self.ibug68 is None:
            raise FacesynthError(f"landmark scheme {self.name!r} has no mapping to ibug68")
        m = np.zeros((IBUG68.n_points, self.n_points))
        for i, idx in enumerate(self.ibug68):
            m[i, list(idx)] = 1.0 / len(idx)
        return m

    def to_ibug68(self, landmarks: np.ndarray) -> np.ndarray:
        """(..., n_points, 2) landmarks -> float32 (..., 68, 2) iBUG points (identity for ibug68).

        The mapping is approximate for other markups (see docs/landmarks.md for its error)."""
        self.check(landmarks, f"{self.name} landmarks")
        lm = np.asarray(landmarks)
        if self is IBUG68:
            return lm.astype(np.float32, copy=False)
        return np.einsum("ip,...pc->...ic", self.ibug68_matrix(), lm.astype(np.float64)).astype(np.float32)


IBUG68 = LandmarkScheme(
    name="ibug68",
    n_points=68,
    regions=MappingProxyType({
        "jaw": JAW, "right_brow": RIGHT_BROW, "left_brow": LEFT_BROW, "brows": BROWS,
        "nose_bridge": NOSE_BRIDGE, "nose_lower": NOSE_LOWER, "nose": NOSE,
        "right_eye": RIGHT_EYE, "left_eye": LEFT_EYE, "eyes": EYES,
        "outer_lips": OUTER_LIPS, "inner_lips": INNER_LIPS, "mouth": MOUTH,
        "eye_corners": EYE_CORNERS, "rigid_inner": RIGID_INNER, "rigid_nose_eyes": RIGID_NOSE_EYES,
        "rigid_fap": RIGID_FAP, "fap_anchors": FAP_ANCHORS, "pose": POSE_POINTS,
    }),
    description="iBUG 300-W 68 points, 0-based (0-16 jaw, 17-26 brows, 27-35 nose, 36-47 eyes, 48-67 mouth)",
    ibug68=tuple((i,) for i in range(68)),
)

# ------------------------------------------------------------ MediaPipe Face Mesh, 478 points
MP_RIGID_INNER = mp.MP_NOSE_BRIDGE + (4, 75, 2, 305) + mp.MP_EYE_CORNERS
"""The points of :data:`RIGID_INNER` in MediaPipe's markup (nose bridge and tip, alae,
subnasale, eye corners): frame-to-frame head alignment."""

MP_RIGID_NOSE_EYES = mp.MP_NOSE_BRIDGE + mp.MP_NOSE_LOWER + mp.MP_EYE_CORNERS
"""The whole nose and the eye corners (as :data:`RIGID_NOSE_EYES`)."""

MEDIAPIPE478 = LandmarkScheme(
    name="mediapipe478",
    n_points=478,
    regions=MappingProxyType({
        "face_oval": mp.MP_FACE_OVAL, "jaw": mp.MP_JAW,
        "right_brow": mp.MP_RIGHT_BROW, "left_brow": mp.MP_LEFT_BROW, "brows": mp.MP_RIGHT_BROW + mp.MP_LEFT_BROW,
        "nose_bridge": mp.MP_NOSE_BRIDGE, "nose_lower": mp.MP_NOSE_LOWER, "nose": mp.MP_NOSE_BRIDGE + mp.MP_NOSE_LOWER,
        "right_eye": mp.MP_RIGHT_EYE, "left_eye": mp.MP_LEFT_EYE, "eyes": mp.MP_RIGHT_EYE + mp.MP_LEFT_EYE,
        "right_iris": mp.MP_RIGHT_IRIS, "left_iris": mp.MP_LEFT_IRIS, "irises": mp.MP_RIGHT_IRIS + mp.MP_LEFT_IRIS,
        "iris_centres": (mp.MP_RIGHT_IRIS[0], mp.MP_LEFT_IRIS[0]),
        "outer_lips": mp.MP_OUTER_LIPS, "inner_lips": mp.MP_INNER_LIPS, "mouth": mp.MP_OUTER_LIPS + mp.MP_INNER_LIPS,
        "mesh": tuple(range(468)),
        "eye_corners": mp.MP_EYE_CORNERS, "rigid_inner": MP_RIGID_INNER, "rigid_nose_eyes": MP_RIGID_NOSE_EYES,
    }),
    description="MediaPipe Face Mesh 478 points, 0-based (0-467 mesh, 468-472 right iris, 473-477 left iris)",
    triangles=mp.MP_TRIANGLES,
    ibug68=mp.IBUG68_FROM_MP478,
)

# ------------------------------------------------------------ dlib's 68 points + MediaPipe's irises, 78 points
IBUG68_IRIS_RIGHT = tuple(range(68, 73))
"""The subject's right iris: centre 68, then its 4 boundary points (MediaPipe 468-472, same order)."""
IBUG68_IRIS_LEFT = tuple(range(73, 78))
"""The subject's left iris: centre 73, then 74-77 (MediaPipe 473-477)."""

IBUG68_IRIS = LandmarkScheme(
    name="ibug68+iris",
    n_points=78,
    regions=MappingProxyType({
        **IBUG68.regions,
        "right_iris": IBUG68_IRIS_RIGHT, "left_iris": IBUG68_IRIS_LEFT, "irises": IBUG68_IRIS_RIGHT + IBUG68_IRIS_LEFT,
        "iris_centres": (IBUG68_IRIS_RIGHT[0], IBUG68_IRIS_LEFT[0]),
    }),
    description="dlib's iBUG 68 points (0-67) + MediaPipe's irises (68-72 right, 73-77 left; centre first)",
    ibug68=tuple((i,) for i in range(68)),
    base="ibug68",
)
"""The lighter gaze variant: points 0-67 exactly as dlib gives them, then MediaPipe's 10 iris
points of the same frame (``facesynth ingest --landmarker dlib+iris``). The face model and
its warp use points 0-67 only (``base``); the irises feed SADM's gaze path."""

SCHEMES: dict[str, LandmarkScheme] = {s.name: s for s in (IBUG68, MEDIAPIPE478, IBUG68_IRIS)}
DEFAULT_SCHEME = IBUG68
N_LANDMARKS = IBUG68.n_points


def get_scheme(name: str) -> LandmarkScheme:
    """The registered scheme ``name``; FacesynthError naming the known ones."""
    try:
        return SCHEMES[name]
    except KeyError:
        raise FacesynthError(f"unknown landmark scheme {name!r} (known: {', '.join(sorted(SCHEMES))})") from None


def scheme_for_points(n_points: int) -> LandmarkScheme | None:
    """The registered scheme with ``n_points`` points, or None (point counts are unique)."""
    return next((s for s in SCHEMES.values() if s.n_points == n_points), None)


def ibug68_view(landmarks: np.ndarray) -> np.ndarray:
    """(..., P, 2) landmarks of the registered scheme with P points -> float64 (..., 68, 2):
    iBUG-68 points as they are, another scheme's through its :meth:`LandmarkScheme.to_ibug68`."""
    lm = np.asarray(landmarks)
    scheme = scheme_for_points(lm.shape[-2]) if lm.ndim >= 2 and lm.shape[-1] == 2 else None
    if scheme is None:
        raise FacesynthError(f"landmarks of shape {lm.shape} are in no registered scheme")
    return lm.astype(np.float64) if scheme is IBUG68 else scheme.to_ibug68(lm).astype(np.float64)


def facing_pairs(ring) -> tuple[np.ndarray, np.ndarray]:
    """The points of a closed contour (a region such as ``inner_lips`` or ``right_eye``: n
    points from one corner over one side to the other corner at n / 2 and back over the
    other side) that face each other across it: point k and point n - k, k = 1 .. n/2 - 1.
    Returns int64 (first side, second side)."""
    ring = np.asarray(ring, np.int64)
    n = len(ring)
    return ring[1 : n // 2], ring[n - 1 : n // 2 : -1]


def folded_triangles(landmarks: np.ndarray, triangles: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """bool (..., T): the fold check of a fixed triangulation. A triangle of ``landmarks``
    (..., P, 2) is folded when its orientation differs from that in ``reference`` (P, 2),
    or, without a reference, when its signed area (b - a) x (c - a) in image axes is not
    positive (the orientation of :attr:`LandmarkScheme.triangles`); degenerate ones count."""
    ref = 1.0 if reference is None else np.sign(triangle_areas(reference, triangles))
    return triangle_areas(landmarks, triangles) * ref <= 0


def triangle_areas(shapes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Signed areas (..., T) of (..., P, 2) shapes' ``triangles`` (T, 3): half of (b - a) x (c - a)
    in image axes, positive for the orientation of :attr:`LandmarkScheme.triangles`."""
    p = np.asarray(shapes, np.float64)
    a, b, c = (p[..., np.asarray(triangles)[:, k], :] for k in range(3))
    return 0.5 * ((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))


FACE_REGIONS = ("eyes", "mouth_interior", "lips", "brows", "rest")
"""The parts every per-region figure uses (evaluation in the frame, SADM's shrinkage and the
ceiling study in the reference frame), drawn by :func:`face_region_masks`."""


def face_region_masks(points68: np.ndarray, shape: tuple[int, int], within: np.ndarray | None = None) -> dict:
    """bool (H, W) masks of :data:`FACE_REGIONS` from one face's iBUG-68 points (68, 2), in
    pixels of an image of ``shape`` (H, W); the one definition of the face's parts.

    ``eyes``: the eye polygons (36-41, 42-47); ``mouth_interior``: the inner-lip polygon
    (60-67) of an open mouth (:func:`mouth_open` above :data:`MOUTH_CLOSED`; a closed mouth
    has none: its inner-lip polygon is the line where the lips meet, and belongs to the lips);
    ``lips``: the outer-lip polygon (48-59) without the interior; ``brows``: each
    brow closed by its eye's upper lid (17-21 + 39-36, 22-26 + 45-42) without the eyes;
    ``rest``: ``within`` (default: everything) without the others. All are cut to ``within``,
    so they partition it. Polygons are filled at pixel centres (4 fractional bits).
    Another scheme's points go through :func:`ibug68_view` first."""
    pts = np.asarray(points68, np.float64)
    IBUG68.check(pts, "face_region_masks")
    h, w = int(shape[0]), int(shape[1])
    inside = np.ones((h, w), bool) if within is None else np.asarray(within, bool)

    def fill(idx):
        m = np.zeros((h, w), np.uint8)
        cv2.fillPoly(m, [np.round(pts[list(idx)] * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
        return m > 0

    eyes = (fill(RIGHT_EYE) | fill(LEFT_EYE)) & inside
    interior = (fill(INNER_LIPS) if float(mouth_open(pts)) > MOUTH_CLOSED else np.zeros((h, w), bool)) & inside & ~eyes
    lips = fill(OUTER_LIPS) & inside & ~eyes & ~interior
    upper_lids = (39, 38, 37, 36), (45, 44, 43, 42)
    brows = (fill(RIGHT_BROW + upper_lids[0]) | fill(LEFT_BROW + upper_lids[1])) & inside & ~eyes & ~interior & ~lips
    return {"eyes": eyes, "mouth_interior": interior, "lips": lips, "brows": brows,
            "rest": inside & ~(eyes | interior | lips | brows)}


INNER_UPPER = (61, 62, 63)  # inner-lip points facing INNER_LOWER across the mouth opening
INNER_LOWER = (67, 66, 65)
MOUTH_CLOSED = 0.03  # mouth_open at or below this: a closed mouth (the neutral frame's rule, the face's parts)


def mouth_open(landmarks: np.ndarray) -> np.ndarray:
    """Mean inner-lip gap (61-67, 62-66, 63-65) / inter-ocular distance: (..., 68, 2) -> (...)."""
    lm = np.asarray(landmarks, np.float64)
    gap = np.linalg.norm(lm[..., list(INNER_UPPER), :] - lm[..., list(INNER_LOWER), :], axis=-1).mean(-1)
    return gap / inter_ocular(lm)


def eye_lids(scheme: LandmarkScheme | None = None) -> tuple:
    """Per eye (right, left) of ``scheme`` (default iBUG-68): its facing eyelid points (upper,
    lower), :func:`facing_pairs` of the eye's contour."""
    scheme = IBUG68 if scheme is None else scheme
    return tuple(facing_pairs(scheme.region(f"{side}_eye")) for side in ("right", "left"))


def eye_openings(landmarks: np.ndarray, scheme: LandmarkScheme | None = None) -> np.ndarray:
    """Each eye's opening: the mean gap of its facing eyelid points (:func:`eye_lids`) across
    the line through its two corners, over the corners' distance: (N, P, 2) or (P, 2) ->
    (N, 2) or (2,) (right eye, left eye; of ``scheme``'s eye regions, default iBUG-68)."""
    lm = np.asarray(landmarks, np.float64)
    scheme = IBUG68 if scheme is None else scheme
    c = scheme.region("eye_corners")
    out = []
    for (c0, c1), (up, lo) in zip((c[:2], c[2:]), eye_lids(scheme), strict=True):
        axis = lm[..., c1, :] - lm[..., c0, :]
        width = np.maximum(np.linalg.norm(axis, axis=-1), 1e-12)
        normal = np.stack([-axis[..., 1], axis[..., 0]], -1) / width[..., None]
        gap = np.abs(((lm[..., up, :] - lm[..., lo, :]) * normal[..., None, :]).sum(-1)).mean(-1)
        out.append(gap / width)
    return np.stack(out, -1)


def inter_ocular(landmarks: np.ndarray) -> np.ndarray:
    """Outer-eye-corner distance of (..., 68, 2) landmarks -> (...)."""
    lm = np.asarray(landmarks, np.float64)
    return np.linalg.norm(lm[..., OUTER_EYE_CORNERS[0], :] - lm[..., OUTER_EYE_CORNERS[1], :], axis=-1)
