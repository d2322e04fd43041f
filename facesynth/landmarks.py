"""Landmark schemes, defined once: how many points, which index is which part of the face,
and the rigid subsets the methods align on.

A landmark array is float32 (N, P, 2) of (x, y) pixel coordinates, 0-based, with P the
scheme's ``n_points``. Today's scheme is iBUG 300-W's 68-point markup (dlib's shape
predictor, the ``.pts`` files of the 300-W data); every module that needs to know which
point is an eye corner or a lip takes the indices from here::

    from facesynth.landmarks import IBUG68, EYES, INNER_LIPS
    lm[:, IBUG68.region("mouth")]

The rigid subsets differ on purpose: each method aligns on the points that its own input
never moves (see the docstring of each constant). A new scheme is one more
:class:`LandmarkScheme` registered in :data:`SCHEMES` (see docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

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
    """

    name: str
    n_points: int
    regions: MappingProxyType = field(repr=False)
    description: str = ""

    def region(self, name: str) -> np.ndarray:
        """int64 indices of region ``name``; FacesynthError naming the known regions."""
        try:
            return np.asarray(self.regions[name], np.int64)
        except KeyError:
            raise FacesynthError(f"landmark scheme {self.name!r} has no region {name!r} "
                                 f"(it has {', '.join(sorted(self.regions))})") from None

    def check(self, landmarks: np.ndarray, where: str) -> None:
        """Raise FacesynthError unless ``landmarks`` is (..., n_points, 2)."""
        shape = np.shape(landmarks)
        if len(shape) < 2 or tuple(shape[-2:]) != (self.n_points, 2):
            raise FacesynthError(f"{where}: landmarks must have shape (..., {self.n_points}, 2) "
                                 f"({self.description}), got {tuple(shape)}")


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
)

SCHEMES: dict[str, LandmarkScheme] = {IBUG68.name: IBUG68}
DEFAULT_SCHEME = IBUG68
N_LANDMARKS = IBUG68.n_points


def get_scheme(name: str) -> LandmarkScheme:
    """The registered scheme ``name``; FacesynthError naming the known ones."""
    try:
        return SCHEMES[name]
    except KeyError:
        raise FacesynthError(f"unknown landmark scheme {name!r} (known: {', '.join(sorted(SCHEMES))})") from None


def inter_ocular(landmarks: np.ndarray) -> np.ndarray:
    """Outer-eye-corner distance of (..., 68, 2) landmarks -> (...)."""
    lm = np.asarray(landmarks, np.float64)
    return np.linalg.norm(lm[..., OUTER_EYE_CORNERS[0], :] - lm[..., OUTER_EYE_CORNERS[1], :], axis=-1)
