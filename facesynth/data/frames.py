"""Frame sources: where a sequence's images come from, decoded lazily.

A source maps an original frame index to a uint8 RGB image (H, W, 3). Video frames
are decoded on demand with a forward-reading cursor (H.264 seeking is slow and not
always frame-exact), so a 1000-frame clip never has to sit in memory whole.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from facesynth.errors import FacesynthError


class FrameSource:
    """Base class. ``size`` is (H, W); ``len()`` the number of frames."""

    size: tuple[int, int]

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def read(self, indices: Sequence[int]) -> Iterator[np.ndarray]:
        """Yield uint8 RGB (H, W, 3) frames for ``indices`` (any order), in that order."""
        raise NotImplementedError


class ArrayFrames(FrameSource):
    """Frames already in memory: uint8 array (T, H, W, 3)."""

    def __init__(self, frames: np.ndarray):
        frames = np.asarray(frames)
        if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
            raise FacesynthError(f"frames must be uint8 (T, H, W, 3), got {frames.dtype} {frames.shape}")
        self.frames = frames
        self.size = frames.shape[1:3]

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, indices: Sequence[int]) -> Iterator[np.ndarray]:
        for i in indices:
            yield self.frames[int(i)]


class ImageFiles(FrameSource):
    """One image file per frame (any format OpenCV reads)."""

    def __init__(self, paths: Sequence[str | os.PathLike]):
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise FacesynthError("no image files given")
        self.size = self._load(0).shape[:2]

    def __len__(self) -> int:
        return len(self.paths)

    def _load(self, i: int) -> np.ndarray:
        img = cv2.imread(str(self.paths[i]), cv2.IMREAD_COLOR)
        if img is None:
            raise FacesynthError(f"{self.paths[i]}: unreadable image")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def read(self, indices: Sequence[int]) -> Iterator[np.ndarray]:
        for i in indices:
            yield self._load(int(i))


class VideoFrames(FrameSource):
    """Frames of a video file decoded with OpenCV, read forward with a cursor."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        cap = self._open()
        self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.n_frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.size = (int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        cap.release()
        self._cap: cv2.VideoCapture | None = None
        self._pos = 0

    def _open(self) -> cv2.VideoCapture:
        if not self.path.is_file():
            raise FacesynthError(f"{self.path}: video file not found")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise FacesynthError(f"{self.path}: unreadable video (OpenCV could not open it)")
        return cap

    def __len__(self) -> int:
        return self.n_frames

    def iter_all(self) -> Iterator[np.ndarray]:
        """Decode every frame in order (the number may differ from the header's count)."""
        cap = self._open()
        try:
            while True:
                ok, bgr = cap.read()
                if not ok:
                    return
                yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        finally:
            cap.release()

    def read(self, indices: Sequence[int]) -> Iterator[np.ndarray]:
        for i in indices:
            i = int(i)
            if self._cap is None or i < self._pos:
                if self._cap is not None:
                    self._cap.release()
                self._cap, self._pos = self._open(), 0
            while self._pos < i:
                if not self._cap.grab():
                    raise FacesynthError(f"{self.path}: frame {i} is past the end of the video ({self._pos} frames)")
                self._pos += 1
            ok, bgr = self._cap.read()
            if not ok:
                raise FacesynthError(f"{self.path}: frame {i} is past the end of the video ({self._pos} frames)")
            self._pos += 1
            yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
