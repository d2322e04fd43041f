"""Video files written whole: an atomic mp4v writer that reopens what it wrote.

``cv2.VideoWriter`` reports no write errors: on a full disk it leaves a file without its
index (the mp4 ``moov`` atom) that plays nothing, and the command would exit 0. Every video
output goes through :func:`atomic_video`, which writes a temporary sibling (as
:func:`facesynth.io.atomic_path`), then reopens it and checks the frame count, the frame
size and that the last frame decodes (:func:`check_video`) before renaming it into place::

    with atomic_video("out.mp4", fps=25.0) as video:
        for rgb in frames:              # uint8 RGB (H, W, 3); the size is the first frame's
            video.write(rgb)
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import Iterator

import numpy as np

from facesynth.errors import DiskFullError, FacesynthError
from facesynth.io import atomic_path

LOW_SPACE = 1 << 20  # bytes free below which an output that does not reopen is put down to a full disk


@contextlib.contextmanager
def ffmpeg_silenced() -> Iterator[None]:
    """Silence file descriptor 2 while OpenCV opens a file: FFmpeg prints its own complaints
    about a broken one (e.g. ``moov atom not found``) there, and the caller reports the
    problem in one line instead."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@contextlib.contextmanager
def opencv_warnings_off() -> Iterator[None]:
    """OpenCV's own log at errors only while a video is written: on a full disk its FFmpeg
    writer warns once per frame it cannot write (``Failed to write frame``), and the check of
    the file afterwards (:func:`check_video`) reports the problem in one line instead."""
    import cv2

    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


def free_bytes(path: str | os.PathLike) -> int | None:
    """Bytes free to an unprivileged user on the file system holding ``path`` (None if unknown)."""
    try:
        st = os.statvfs(path)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def raise_unless_space(path: str | os.PathLike, name: str | os.PathLike) -> None:
    """:class:`DiskFullError` naming ``name`` when ``path``'s file system has less than
    :data:`LOW_SPACE` bytes free (the likely cause of a write that silently failed there)."""
    free = free_bytes(Path(path).parent)
    if free is not None and free < LOW_SPACE:
        raise DiskFullError(name)


def check_video(path: str | os.PathLike, n_frames: int, size: tuple[int, int], name: str | os.PathLike) -> None:
    """Reopen the video at ``path`` and check it holds ``n_frames`` frames of (W, H) ``size``
    and that its last frame decodes.

    Raises :class:`DiskFullError` (naming ``name``) when the file system is (nearly) full,
    FacesynthError naming ``name`` and what was found otherwise.
    """
    import cv2

    with ffmpeg_silenced():
        cap = cv2.VideoCapture(str(path))
    try:
        opened = cap.isOpened()
        found = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if opened else 0
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))) if opened else (0, 0)
        last = False
        if found == n_frames and n_frames > 0:
            cap.set(cv2.CAP_PROP_POS_FRAMES, n_frames - 1)
            last = cap.read()[0]
    finally:
        cap.release()
    if found == n_frames and got == tuple(size) and last:
        return
    raise_unless_space(path, name)
    what = f"{found} frames of {got[0]}x{got[1]}" if opened else "nothing readable"
    if opened and found == n_frames and got == tuple(size):
        what += " whose last frame does not decode"
    raise FacesynthError(f"{name}: the video written does not reopen as {n_frames} frames of {size[0]}x{size[1]} "
                         f"(found {what}); it was not kept")


class VideoOut:
    """An mp4v ``cv2.VideoWriter`` on ``tmp`` that counts its frames; opened at the first
    frame when ``size`` (W, H) is not given. ``name`` is the final path, for messages."""

    def __init__(self, tmp: Path, fps: float, size: tuple[int, int] | None, name: str | os.PathLike):
        self.tmp, self.fps, self.size, self.name = tmp, float(fps), size, name
        self.frames = 0
        self._writer = None
        self._finished = False
        if size is not None:
            self._open(size)

    def _open(self, size: tuple[int, int]) -> None:
        import cv2

        self.size = (int(size[0]), int(size[1]))
        with opencv_warnings_off(), ffmpeg_silenced():
            self._writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, self.size)
        if not self._writer.isOpened():
            raise_unless_space(self.tmp, self.name)  # a full disk: said so, not put down to the name
            raise FacesynthError(f"{self.name}: OpenCV cannot write an mp4v video here (use a .mp4 or .avi name)")

    def write(self, rgb: np.ndarray) -> None:
        """Append one uint8 RGB (H, W, 3) frame of the video's size."""
        import cv2

        h, w = rgb.shape[:2]
        if self._writer is None:
            self._open((w, h))
        if (w, h) != self.size:
            raise FacesynthError(f"{self.name}: a {w}x{h} frame in a {self.size[0]}x{self.size[1]} video")
        with opencv_warnings_off():
            self._writer.write(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
        self.frames += 1

    def release(self) -> None:
        if self._writer is not None:
            with opencv_warnings_off(), ffmpeg_silenced():
                self._writer.release()

    def finish(self) -> None:
        """Close the file and check it (:func:`check_video`); once."""
        if self._finished:
            return
        self.release()
        if not self.frames:
            raise FacesynthError(f"{self.name}: no frames to write")
        check_video(self.tmp, self.frames, self.size, self.name)
        self._finished = True


@contextlib.contextmanager
def atomic_video(path: str | os.PathLike, fps: float, size: tuple[int, int] | None = None) -> Iterator[VideoOut]:
    """Yield a :class:`VideoOut` writing a temporary sibling of ``path``; on success it is
    closed, reopened and checked (:meth:`VideoOut.finish`, which the caller may call
    earlier, e.g. before writing other outputs that depend on it), then renamed onto
    ``path``. On any error nothing is left."""
    with atomic_path(path) as tmp:
        video = VideoOut(tmp, fps, size, path)
        try:
            yield video
        finally:
            video.release()
        video.finish()
