"""Output helpers for expression transfer: atomic MP4 writing and the contact sheet
(driver frame | geometry-only warp | ERI result)."""

from __future__ import annotations

import os
from typing import Iterable

import cv2
import numpy as np

from facesynth.sheet import grid, write_png
from facesynth.videofile import atomic_video


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float) -> int:
    """Write uint8 RGB (H, W, 3) frames to an MP4 (OpenCV ``mp4v``) atomically; returns the
    number of frames. The file appears only once every frame is written and the video
    reopens with them all (:func:`facesynth.videofile.atomic_video`)."""
    with atomic_video(path, fps) as video:
        for f in frames:
            video.write(f)
    return video.frames


def face_box(landmarks: np.ndarray, shape: tuple[int, ...], margin: float = 0.35) -> tuple[int, int, int, int]:
    """Square crop (x0, y0, x1, y1) around (68, 2) landmarks with ``margin`` (fraction of the
    box side) added above (forehead) and around, clipped to the image."""
    lo, hi = landmarks.min(0), landmarks.max(0)
    side = float(max(hi - lo)) * (1 + 2 * margin)
    c = 0.5 * (lo + hi) - [0, 0.08 * side]
    x0, y0 = int(max(0, c[0] - side / 2)), int(max(0, c[1] - side / 2))
    x1, y1 = int(min(shape[1], c[0] + side / 2)), int(min(shape[0], c[1] + side / 2))
    return x0, y0, x1, y1


def crop(image: np.ndarray, box: tuple[int, int, int, int], size: int) -> np.ndarray:
    x0, y0, x1, y1 = box
    return cv2.resize(image[y0:y1, x0:x1], (size, size), interpolation=cv2.INTER_AREA)


def pick_sheet_rows(faps: np.ndarray, n: int) -> np.ndarray:
    """``n`` frames spread over time: the most expressive (largest FAP norm) of each of
    ``n`` equal time chunks. (N, 36) -> int (n,) sorted indices."""
    norm = np.linalg.norm(np.asarray(faps, np.float64), axis=1)
    chunks = np.array_split(np.arange(len(faps)), min(n, len(faps)))
    return np.array([c[np.argmax(norm[c])] for c in chunks if len(c)])


def contact_sheet(
    path: str | os.PathLike, driver: list[np.ndarray], driver_lm: np.ndarray, geometry: list[np.ndarray],
    eri: list[np.ndarray], target_lm: np.ndarray, size: int = 256,
) -> None:
    """PNG with one row per frame: driver frame | geometry-only warp | ERI result, each a face
    crop of ``size`` px (driver crops around its own landmarks (n, 68, 2); the target
    crops around ``target_lm`` (n, 68, 2))."""
    rows = []
    for d, dl, g, e, tl in zip(driver, driver_lm, geometry, eri, target_lm, strict=True):
        tb = face_box(tl, g.shape)
        rows.append([crop(d, face_box(dl, d.shape), size), crop(g, tb, size), crop(e, tb, size)])
    write_png(path, grid(rows, ("driver", "geometry-only warp", "ERI")))
