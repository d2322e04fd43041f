"""478-point (MediaPipe scheme) landmarks without MediaPipe, for unit tests: MediaPipe's
canonical face mesh (../shared/data/mesh, frontal projection) with iris points in the eyes,
bent onto any 68-point face by a thin-plate spline through the 68 points that
:meth:`LandmarkScheme.to_ibug68` maps it to. The synthetic subject's frames are drawn from
its 68 points, so its 478 points follow the drawn face."""

import numpy as np
from scipy.interpolate import RBFInterpolator

from facesynth.data.sequence import FaceSequence
from facesynth.landmarks import MEDIAPIPE478


def template478(mesh_npz) -> np.ndarray:
    """float64 (478, 2): the canonical mesh seen from the front (x right, y down, cm), each
    iris a centre at its eye's centroid and 4 points 0.6 cm away."""
    v = np.load(mesh_npz)["vertices"]
    p = np.stack([v[:, 0], -v[:, 1]], -1).astype(np.float64)
    irises = []
    for eye in ("right_eye", "left_eye"):
        c = p[MEDIAPIPE478.region(eye)].mean(0)
        irises += [c] + [c + d for d in ([0.6, 0], [0, -0.6], [-0.6, 0], [0, 0.6])]
    return np.concatenate([p, np.asarray(irises)])


def to478(landmarks68: np.ndarray, template: np.ndarray) -> np.ndarray:
    """(N, 68, 2) -> float32 (N, 478, 2): the template bent onto each frame's 68 points."""
    src = MEDIAPIPE478.to_ibug68(template).astype(np.float64)
    out = [RBFInterpolator(src, lm.astype(np.float64), kernel="thin_plate_spline")(template) for lm in landmarks68]
    return np.asarray(out, np.float32)


def dense_sequence(seq68: FaceSequence, mesh_npz) -> FaceSequence:
    """``seq68`` (ibug68, with frames) as a mediapipe478 sequence over the same frames."""
    lm = to478(seq68.landmarks, template478(mesh_npz))
    return FaceSequence(lm, seq68.frame_index, seq68.frames, seq68.fps, seq68.name + "_478", dict(seq68.meta), "mediapipe478")
