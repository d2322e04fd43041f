"""The whole talking head in one ONNX graph, run torch-free
(:mod:`facesynth.onnx.talking_head` writes the file)::

    from facesynth.runtime.talking_head import TalkingHead
    th = TalkingHead("head.onnx", driver_neutral=lm0)   # or None: chosen from the first frames
    for lm in driver_landmarks:                         # (P, 2) driver frame pixels
        frame, avatar_lm = th.step(lm)                  # uint8 (H, W, 3), float32 (P, 2)

The graph computes what :class:`facesynth.runtime.Reenactor` computes with the full-frame
warp and relative motion (retargeting, shape clamp, synthesis, warp of the avatar's neutral
frame, feathered colour-matched seam with the file's fixed ``feather``); the driver's neutral
is chosen as there when none is given.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from facesynth.contract import TALKING_HEAD_FORMAT, TALKING_HEAD_INPUTS
from facesynth.errors import FacesynthError
from facesynth.neutral import select_neutral
from facesynth.runtime.reenact import NEUTRAL_FRAMES, Avatar
from facesynth.runtime.renderer import _decode, _session, check_batch


class TalkingHead:
    """Driver landmarks -> composited avatar frames, one ONNX Runtime call per batch.

    path : the talking-head ONNX file; driver_neutral : (P, 2), optional; threads : ONNX
    Runtime's intra-op threads; neutral_frames : frames collected to choose the driver's
    neutral when none is given.
    """

    def __init__(self, path: str | os.PathLike, driver_neutral=None, threads: int = 1,
                 neutral_frames: int = NEUTRAL_FRAMES):
        self.path = Path(path)
        self.session = _session(self.path, threads, False)
        self.metadata = _decode(self.session.get_modelmeta().custom_metadata_map)
        if self.metadata.get("format") != TALKING_HEAD_FORMAT:
            raise FacesynthError(f"{self.path}: not a talking-head graph (format {self.metadata.get('format')!r}, "
                                 f"expected {TALKING_HEAD_FORMAT!r})")
        self.n_points = int(self.metadata.get("n_landmarks", 68))
        self.avatar = Avatar(self.metadata, str(self.path))
        self.scheme = self.avatar.scheme  # the landmark scheme's name, as the metadata gives it
        self.background = self.avatar.background  # uint8 (H, W, 3) its neutral frame: shown where a driver has no face
        self.last_model_s = 0.0  # seconds of the last ONNX Runtime call
        self.feather = float(self.metadata["feather"])
        self.frame_size = tuple(int(v) for v in self.metadata["frame_size"])  # (W, H)
        self.neutral_frames = int(neutral_frames)
        self._seen: list[np.ndarray] = []  # driver frames collected while choosing its neutral
        self._collecting = driver_neutral is None
        self.driver_neutral = None
        if driver_neutral is not None:
            self.use_neutral(driver_neutral)

    def use_neutral(self, driver_neutral) -> "TalkingHead":
        """Take (P, 2) ``driver_neutral`` as the driver's neutral from now on; returns self."""
        self.driver_neutral = self._points(np.asarray(driver_neutral)[None], "driver_neutral")[0]
        self._collecting, self._seen = False, []
        return self

    def _points(self, values, field: str) -> np.ndarray:
        return check_batch(values, field, (self.n_points, 2), "frame pixels", f"(B, {self.n_points}, 2)",
                           " (a frame without a face)")

    def run(self, driver) -> tuple[np.ndarray, np.ndarray]:
        """(B, P, 2) driver landmarks -> uint8 (B, H, W, 3) frames, float32 (B, P, 2)
        avatar landmarks; needs the driver's neutral (given, or chosen by :meth:`step`)."""
        if self.driver_neutral is None:
            raise FacesynthError(f"{self.path}: no driver neutral yet (give driver_neutral, or call step)")
        d = self._points(driver, "driver landmarks")
        t0 = time.perf_counter()
        frames, avatar = self.session.run(None, dict(zip(TALKING_HEAD_INPUTS, (d, self.driver_neutral), strict=True)))
        self.last_model_s = time.perf_counter() - t0
        return frames, avatar

    def step(self, landmarks) -> tuple[np.ndarray, np.ndarray]:
        """One (P, 2) driver frame -> (uint8 (H, W, 3) frame, float32 (P, 2) avatar landmarks)."""
        lm = self._points(np.asarray(landmarks)[None], "driver landmarks")
        if self._collecting:  # no neutral given: choose among the frames seen so far
            self._seen.append(lm[0])
            self.driver_neutral = self._seen[select_neutral(np.stack(self._seen))[0]]
            if len(self._seen) >= self.neutral_frames:
                self._collecting, self._seen = False, []
        frames, avatar = self.run(lm)
        return frames[0], avatar[0]
