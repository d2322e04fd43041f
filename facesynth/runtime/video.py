"""Video input and pictures of ``facesynth app``: the driver's frames and landmarks, the
side-by-side and contact-sheet pictures (the output video is :mod:`facesynth.videofile`'s).

Frames are uint8 RGB (H, W, 3) here; OpenCV's BGR stays inside these functions.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np

from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.sheet import grid
from facesynth.videofile import raise_unless_space


def landmarker_passes(scheme: str) -> tuple[bool, bool]:
    """(dlib, MediaPipe): the landmarkers a model in ``scheme`` needs (each checked before any
    frame: a missing extra is a one-line error): dlib (the ``ingest`` extra) for ``ibug68``,
    MediaPipe (the ``mediapipe`` extra) for ``mediapipe478``, both for ``ibug68+iris``."""
    if scheme not in ("ibug68", "mediapipe478", "ibug68+iris"):
        raise FacesynthError(f"--video: no landmarker for a model in scheme {scheme!r}; give --landmarks")
    use_dlib, use_mp = scheme != "mediapipe478", scheme != "ibug68"
    if use_dlib:
        try:
            from facesynth.data import detect
        except ModuleNotFoundError as exc:
            raise MissingExtraError("ingest", exc.name or "facesynth.data.detect") from None
        detect.check_extra()
    if use_mp:
        from facesynth.data import detect_mediapipe

        detect_mediapipe.check_extra()
    return use_dlib, use_mp


def detect_video_landmarks(frames: Callable[[], Iterable[np.ndarray]], scheme: str = "ibug68",
                           on_frame: Callable[[int, str], None] | None = None) -> np.ndarray:
    """Landmarks (T, P, 2) of driver frames in the model's ``scheme``; NaN rows where no face
    (landmarkers: :func:`landmarker_passes`; dlib's 68 points and MediaPipe's irises for
    ``ibug68+iris``). ``frames()`` gives the uint8 RGB (H, W, 3) frames afresh for each pass
    (decoded as they are used, so a long video never sits in memory whole);
    ``on_frame(index, source)`` is called after each frame of each pass."""
    use_dlib, use_mp = landmarker_passes(scheme)
    dlib = mp = None
    if use_dlib:
        from facesynth.data import detect

        dlib = np.asarray(detect.detect_landmarks(frames(), on_frame=on_frame).landmarks, np.float32)
    if use_mp:
        from facesynth.data import detect_mediapipe

        mp = np.asarray(detect_mediapipe.detect_landmarks_mediapipe(frames(), on_frame=on_frame).landmarks, np.float32)
    if use_dlib and use_mp:
        from facesynth.data.iris import combine_landmarks

        return combine_landmarks(dlib, mp)
    return dlib if use_dlib else mp


def draw_landmarks(background: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """The driver as dots (P, 2) on a copy of ``background`` (side-by-side view without a video)."""
    out = background.copy()
    if np.isfinite(landmarks).all():
        for x, y in np.round(landmarks).astype(int):
            cv2.circle(out, (int(x), int(y)), 2, (255, 64, 32), -1, lineType=cv2.LINE_AA)
    return out


def fit_into(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` scaled to fit (H, W) with its aspect kept, centred on black."""
    h, w = size
    ih, iw = image.shape[:2]
    if (ih, iw) == (h, w):
        return image
    s = min(h / ih, w / iw)
    nh, nw = max(1, int(round(ih * s))), max(1, int(round(iw * s)))
    out = np.zeros((h, w, 3), np.uint8)
    y, x = (h - nh) // 2, (w - nw) // 2
    out[y:y + nh, x:x + nw] = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
    return out


def contact_sheet(top: list[np.ndarray], bottom: list[np.ndarray], width: int = 240) -> np.ndarray:
    """Two rows of thumbnails (uint8 RGB): drivers above renderings (:func:`facesynth.sheet.grid`)."""
    def thumb(img):
        h, w = img.shape[:2]
        return cv2.resize(img, (width, int(round(h * width / w))), interpolation=cv2.INTER_AREA)

    return grid([[thumb(i) for i in r] for r in (top, bottom)])


def write_image(tmp: Path, rgb: np.ndarray, name: str | os.PathLike) -> None:
    """uint8 RGB ``rgb`` to ``tmp`` (format by extension), checked by reading it back."""
    if not cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)) or cv2.imread(str(tmp)) is None:
        raise_unless_space(tmp, name)
        raise FacesynthError(f"{name}: could not write the image")
