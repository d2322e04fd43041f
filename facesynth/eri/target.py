"""The target face of an ERI transfer or export: its neutral image and landmarks, from an
image (landmarks given or detected) or an ingest folder (``transfer-expression --target`` and
``facesynth export --target`` name it the same way)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facesynth.errors import FacesynthError, MissingExtraError

IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}


def load_target(target, target_landmarks=None, target_frame: int | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """The target's neutral image (uint8 RGB) and (68, 2) landmarks, and a description.

    ``target``: an image (landmarks from ``target_landmarks``, row ``target_frame``, or
    detected) or a folder in ingest layout (row ``target_frame``, default automatic)."""
    from facesynth.data import load_landmarks, load_sequence
    from facesynth.eri.geometry import select_neutral

    path = Path(target)
    if path.is_dir():
        seq = load_sequence(path, scheme="ibug68")
        if not seq.has_frames:
            raise FacesynthError(f"{path}: target folder has landmarks but no video/images")
        row = target_frame if target_frame is not None else select_neutral(seq.landmarks)[0]
        if not 0 <= row < len(seq):
            raise FacesynthError(f"--target-frame {row} is outside {path} (0..{len(seq) - 1})")
        return seq.frame(row), seq.landmarks[row], f"{path} row {row}"
    if not path.is_file():
        raise FacesynthError(f"{path}: no such target image or folder")
    if path.suffix.lower() not in IMAGE_EXT:
        raise FacesynthError(f"{path}: target must be an image ({', '.join(sorted(IMAGE_EXT))}) or an ingest folder")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FacesynthError(f"{path}: unreadable image")
    img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if target_landmarks:
        lm = load_landmarks(target_landmarks, scheme="ibug68")
        row = target_frame or 0
        if not 0 <= row < len(lm) or not np.isfinite(lm[row]).all():
            raise FacesynthError(f"{target_landmarks}: no valid landmarks at row {row}")
        return img, lm[row], f"{path} with {target_landmarks}"
    return img, _detect(img, path), f"{path} (landmarks detected)"


def _detect(img: np.ndarray, path: Path) -> np.ndarray:
    try:
        import dlib  # noqa: F401
    except ImportError:
        raise MissingExtraError("ingest", "dlib") from None
    try:
        from facesynth.data.detect import LandmarkDetector
    except ImportError:
        raise FacesynthError(f"{path}: landmark detection is not available in this build; pass --target-landmarks") from None
    det = LandmarkDetector()
    box, _, _ = det.detect(img)
    if box is None:
        raise FacesynthError(f"{path}: no face found in the target image; pass --target-landmarks")
    return det.landmarks(img, box)
