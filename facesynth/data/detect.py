"""Face detection and 68-point landmark fitting with dlib (the optional ``ingest`` extra).

Detector: dlib's HOG + linear SVM frontal face detector (Dalal & Triggs, CVPR 2005;
dlib ``get_frontal_face_detector``), run on the RGB frame downscaled to a maximum side
of 640 px, first without upsampling and, when it finds nothing, with one 2x upsampling;
when both miss, the previous frame's box is reused (for at most ``reuse_limit``
consecutive frames). With several faces, the one nearest the previous frame's box is
kept (the largest on the first frame).

Landmarks: dlib's ``shape_predictor`` (ensemble of regression trees, Kazemi & Sullivan,
CVPR 2014) with ``shape_predictor_68_face_landmarks.dat`` (iBUG 300-W markup) as shipped
by the ``face_recognition_models`` package, run on the full-resolution RGB frame. dlib
returns integer pixel coordinates (+-0.5 px rounding).

The model file is located on disk with ``importlib.util.find_spec`` without importing
``face_recognition_models`` (its ``__init__`` needs ``pkg_resources``, which recent
setuptools no longer provides); nothing is ever downloaded.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from importlib import metadata
from importlib.util import find_spec
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.landmarks import N_LANDMARKS

PREDICTOR_FILE = "shape_predictor_68_face_landmarks.dat"
SOURCES = ("hog_up0", "hog_up1", "previous_box", "miss")


def _import_dlib():
    try:
        import dlib
    except ImportError:
        raise MissingExtraError("ingest", "dlib") from None
    return dlib


def predictor_path() -> Path:
    """Path of ``shape_predictor_68_face_landmarks.dat`` inside ``face_recognition_models``."""
    try:
        spec = find_spec("face_recognition_models")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        raise MissingExtraError("ingest", "face_recognition_models")
    path = Path(spec.origin).parent / "models" / PREDICTOR_FILE
    if not path.is_file():
        raise FacesynthError(
            f"{path}: dlib's 68-point model is missing from the face_recognition_models package "
            "(reinstall it: pip install --force-reinstall face_recognition_models)"
        )
    return path


def check_extra() -> None:
    """Raise :class:`MissingExtraError` unless dlib and the 68-point model are installed
    (cheap: loads neither the detector nor the 100 MB predictor)."""
    _import_dlib()
    predictor_path()


def detector_versions() -> dict[str, str]:
    """Versions of the detection stack (dlib, face_recognition_models, OpenCV)."""
    out = {"opencv": cv2.__version__}
    dlib = _import_dlib()
    out["dlib"] = getattr(dlib, "__version__", "unknown")
    for dist in ("dlib-bin", "dlib", "face_recognition_models"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return out


@dataclass
class Detections:
    """Per-frame results of :func:`detect_landmarks`.

    Attributes
    ----------
    landmarks : np.ndarray
        float32 (T, 68, 2), (x, y) 0-based pixels; NaN rows where no face.
    boxes : np.ndarray
        float32 (T, 4) face boxes (left, top, right, bottom) in full-resolution pixels; NaN rows where none.
    sources : list of str
        How each frame's box was found: one of ``SOURCES``.
    n_faces : np.ndarray
        int (T,) number of faces the detector returned (0 for reused/missed boxes).
    timing_s : dict
        Total seconds spent in ``detect`` and ``landmarks``.
    source_names : tuple of str
        The sources this landmarker reports (``SOURCES`` for dlib).
    """

    landmarks: np.ndarray
    boxes: np.ndarray
    sources: list[str]
    n_faces: np.ndarray
    timing_s: dict = field(default_factory=dict)
    source_names: tuple = SOURCES

    def counts(self) -> dict[str, int]:
        return {s: int(sum(1 for x in self.sources if x == s)) for s in self.source_names}

    @property
    def n_processed(self) -> int:
        return sum(1 for x in self.sources if x != "skipped")

    @property
    def detection_rate(self) -> float:
        """Fraction of processed (not skipped) frames that got landmarks."""
        n = self.n_processed
        return float(np.isfinite(self.landmarks[:, 0, 0]).sum() / n) if n else 0.0


class LandmarkDetector:
    """dlib HOG face detector + 68-point shape predictor with a one-box temporal memory.

    Parameters
    ----------
    max_side : int
        Frames are downscaled (``cv2.INTER_AREA``) so that their longer side is at most
        this before detection; boxes are scaled back and the predictor runs at full size.
    reuse_limit : int
        Reuse the previous box for at most this many consecutive missed frames.
    """

    def __init__(self, max_side: int = 640, reuse_limit: int = 15):
        self._dlib = _import_dlib()
        self._detector = self._dlib.get_frontal_face_detector()
        self._predictor = self._dlib.shape_predictor(str(predictor_path()))
        self.max_side = int(max_side)
        self.reuse_limit = int(reuse_limit)
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame's box (start of a new video)."""
        self._prev: np.ndarray | None = None
        self._reused = 0

    def describe(self) -> str:
        v = detector_versions()
        return (
            f"dlib {v['dlib']} HOG frontal detector on RGB frame downscaled to max side {self.max_side} "
            f"(upsample 0, then 1), else previous frame's box (<= {self.reuse_limit} frames); predictor "
            f"{PREDICTOR_FILE} from face_recognition_models {v.get('face_recognition_models', '?')} on the "
            "full-resolution frame; largest face / nearest previous face kept"
        )

    def boxes(self, rgb: np.ndarray) -> tuple[np.ndarray, str]:
        """Every face box (K, 4) (left, top, right, bottom) in full-resolution pixels found by the
        detector on the downscaled frame (upsample 0, then 1 when 0 finds none), and which
        pass found them ("hog_up0", "hog_up1"; "miss" with K = 0). No temporal memory."""
        h, w = rgb.shape[:2]
        scale = min(1.0, self.max_side / max(h, w))
        small = rgb if scale >= 1.0 else cv2.resize(rgb, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        small = np.ascontiguousarray(small)
        for up, source in ((0, "hog_up0"), (1, "hog_up1")):
            dets = self._detector(small, up)
            if len(dets):
                return np.array([[d.left(), d.top(), d.right(), d.bottom()] for d in dets], np.float64) / scale, source
        return np.zeros((0, 4)), "miss"

    def _pick(self, boxes: np.ndarray) -> np.ndarray:
        if len(boxes) > 1 and self._prev is not None:
            c = 0.5 * (boxes[:, :2] + boxes[:, 2:])
            pc = 0.5 * (self._prev[:2] + self._prev[2:])
            return boxes[int(np.argmin(np.linalg.norm(c - pc, axis=1)))]
        areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        return boxes[int(np.argmax(areas))]

    def detect(self, rgb: np.ndarray) -> tuple[np.ndarray | None, str, int]:
        """Face box (left, top, right, bottom) in full-resolution pixels, its source, and
        the number of faces detected, for one uint8 RGB (H, W, 3) frame."""
        found, source = self.boxes(rgb)
        if len(found):
            box = self._pick(found)
            self._prev, self._reused = box, 0
            return box, source, len(found)
        if self._prev is not None and self._reused < self.reuse_limit:
            self._reused += 1
            return self._prev, "previous_box", 0
        return None, "miss", 0

    def landmarks(self, rgb: np.ndarray, box: np.ndarray) -> np.ndarray:
        """float32 (68, 2) landmarks in the box (integer-valued, as dlib returns them)."""
        left, top, right, bottom = (int(round(v)) for v in box)
        shape = self._predictor(np.ascontiguousarray(rgb), self._dlib.rectangle(left, top, right, bottom))
        return np.array([[p.x, p.y] for p in shape.parts()], np.float32)


def detect_landmarks(
    frames: Iterable[np.ndarray | None],
    detector: LandmarkDetector | None = None,
    on_frame: Callable[[int, str], None] | None = None,
) -> Detections:
    """Detect the face and fit 68 landmarks in each frame of a sequence.

    Parameters
    ----------
    frames : iterable of np.ndarray or None
        uint8 RGB (H, W, 3) frames in temporal order; ``None`` marks a frame to skip
        (its row is NaN and it does not break the box memory).
    detector : LandmarkDetector, optional
        Reused across calls if given (it keeps the previous box; call ``reset()``
        between videos); a new one otherwise.
    on_frame : callable, optional
        Called as ``on_frame(index, source)`` after each frame (progress bars).

    Returns
    -------
    Detections
        landmarks (T, 68, 2) float32 with NaN rows where no face, boxes, sources.
    """
    det = detector or LandmarkDetector()

    def fit(rgb: np.ndarray):
        t0 = time.perf_counter()
        box, source, n = det.detect(rgb)
        t1 = time.perf_counter()
        lm = None if box is None else det.landmarks(rgb, box)
        return lm, box, source, n, t1 - t0, time.perf_counter() - t1

    return collect_detections(frames, fit, N_LANDMARKS, SOURCES, on_frame)


def collect_detections(
    frames: Iterable[np.ndarray | None],
    fit: Callable[[np.ndarray], tuple],
    n_points: int,
    source_names: tuple,
    on_frame: Callable[[int, str], None] | None = None,
) -> Detections:
    """The frame loop every landmarker shares: check each uint8 RGB (H, W, 3) frame, call
    ``fit(rgb) -> (landmarks (P, 2) or None, box (4,) or None, source, n_faces, detect_s,
    landmarks_s)``, give skipped frames (``None``) and misses NaN rows, and gather the
    results and their times into :class:`Detections` (landmarks (T, ``n_points``, 2))."""
    lms, boxes, sources, n_faces = [], [], [], []
    t_det = t_lm = 0.0
    nan_lm = np.full((n_points, 2), np.nan, np.float32)
    for i, rgb in enumerate(frames):
        if rgb is None:
            lms.append(nan_lm)
            boxes.append(np.full(4, np.nan))
            sources.append("skipped")
            n_faces.append(0)
            continue
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise FacesynthError(f"frame {i}: expected uint8 RGB (H, W, 3), got {rgb.dtype} {rgb.shape}")
        lm, box, source, n, dt_det, dt_lm = fit(rgb)
        t_det += dt_det
        t_lm += dt_lm
        lms.append(nan_lm if lm is None else lm)
        boxes.append(np.full(4, np.nan) if box is None else box)
        sources.append(source)
        n_faces.append(n)
        if on_frame is not None:
            on_frame(i, source)
    return Detections(
        landmarks=np.stack(lms).astype(np.float32) if lms else np.zeros((0, n_points, 2), np.float32),
        boxes=np.stack(boxes).astype(np.float32) if boxes else np.zeros((0, 4), np.float32),
        sources=sources,
        n_faces=np.asarray(n_faces, dtype=np.int64),
        timing_s={"detect": t_det, "landmarks": t_lm},
        source_names=source_names,
    )
