"""The per-frame work of ``facesynth app``, as one object: an exported avatar and how it is
driven, driver landmarks in, the avatar's frames out (numpy, ONNX Runtime and OpenCV; no
torch). The command line (:mod:`facesynth.runtime.app`) reads the driver, picks the
background and writes the outputs around it::

    p = AvatarPipeline("avatar.onnx")                      # or a talking-head file
    p.start(driver_neutral, background=p.avatar.background)  # (P, 2); uint8 (H, W, 3)
    for frame in p.frames(driver_landmarks):               # (T, P, 2) -> uint8 (H, W, 3) each
        ...

The engine follows the file and the motion:

* a talking-head file (``facesynth export RUN --talking-head``): :class:`TalkingHead`, one ONNX
  Runtime call per frame, in the avatar's own frame with relative motion;
* a face model driven with relative motion, or in the avatar's own frame (its metadata has the
  avatar's neutral and frame and no still background is asked for): :class:`Reenactor`, the
  numpy pipeline (retargeting, the face model's graph, the full-frame warp, the seam);
* otherwise the driver's landmarks as they are, the face composited into a still background
  (:func:`render_frames`).
"""

from __future__ import annotations

import os
import time
from typing import Iterator

import numpy as np

from facesynth.compositing import STILL_FEATHER, blend_rendered
from facesynth.contract import TALKING_HEAD_FORMAT
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.retarget import RETARGET_SCHEMES
from facesynth.runtime.reenact import Avatar, Reenactor, reenact_frames
from facesynth.runtime.renderer import Renderer, read_metadata
from facesynth.runtime.talking_head import TalkingHead


def render_frames(renderer, landmarks: np.ndarray, background: np.ndarray, feather: float = STILL_FEATHER,
                  latencies: list | None = None) -> Iterator[np.ndarray]:
    """uint8 (H, W, 3) frames, one per landmark row (the background where a row is NaN): the
    face rendered on the landmarks as they are, composited into the still ``background``.

    ``latencies`` (a list) collects (model seconds, frame seconds) per rendered frame.
    """
    for lm in landmarks:
        t0 = time.perf_counter()
        if not np.isfinite(lm).all():
            frame = background.copy()
        else:
            rendered = renderer.render(lm[None])
            t1 = time.perf_counter()
            frame = blend_rendered(*rendered, background, feather=feather, still=True)
            if latencies is not None:
                latencies.append((t1 - t0, time.perf_counter() - t0))
        yield frame


def latency_summary(latencies: list) -> dict:
    """p50/p90/p99 (ms) of the model call and of the whole frame."""
    if not latencies:
        return {"frames": 0}
    a = np.asarray(latencies) * 1e3
    out = {"frames": len(a)}
    for i, name in enumerate(("model_ms", "frame_ms")):
        out[name] = {f"p{q}": round(float(np.percentile(a[:, i], q)), 3) for q in (50, 90, 99)}
    return out


class AvatarPipeline:
    """An exported avatar and how it is driven (module docstring).

    model : an exported face model or talking-head file; motion : "relative", "absolute" or
    None (relative when the model's metadata holds its avatar's neutral, else absolute);
    still : composite into a still background (``start``'s), not the avatar's own frame
    warped with the face; feather, match_colour : the seam (face models; ``None``: the
    engine's default); threads : ONNX Runtime's intra-op threads.

    Attributes: ``head`` (TalkingHead or None), ``renderer`` (Renderer or None),
    ``metadata``, ``scheme`` (name), ``n_points``, ``avatar`` (:class:`Avatar`), ``motion``,
    ``full_frame`` (the avatar's own frame, warped with the face).
    """

    def __init__(self, model: str | os.PathLike, motion: str | None = None, still: bool = False,
                 feather: float | None = None, match_colour: bool = True, threads: int = 1):
        self.model = str(model)
        self.head = TalkingHead(model, threads=threads) if read_metadata(model).get("format") == TALKING_HEAD_FORMAT \
            else None
        self.renderer = None if self.head else Renderer(model, threads=threads)
        self.metadata = self.head.metadata if self.head else self.renderer.metadata
        self.scheme = self.head.scheme if self.head else self.renderer.scheme.name
        self.n_points = get_scheme(self.scheme).n_points
        self.avatar = Avatar(self.metadata, self.model)
        if motion == "relative" and self.scheme not in RETARGET_SCHEMES:
            raise FacesynthError(f"--motion relative: retargeting takes {' or '.join(RETARGET_SCHEMES)} landmarks, and "
                                 f"{model} takes {self.scheme} ones; use --motion absolute (a driver in the same scheme)")
        self.motion = motion or ("relative" if self.head or self.avatar.neutral is not None else "absolute")
        if self.motion == "relative":
            self.avatar.require_neutral()
        self.full_frame = bool(self.head) or (not still and self.avatar.neutral is not None
                                              and self.avatar.background is not None)
        self.feather, self.match_colour = feather, match_colour
        self.engine = None
        self.background = None

    def start(self, driver_neutral: np.ndarray | None, background: np.ndarray) -> None:
        """Begin a drive: the driver's neutral (P, 2; None with absolute motion) and the
        background of frames without a face (uint8 (H, W, 3); the still background, or the
        avatar's own frame)."""
        if self.head:
            self.engine = self.head.use_neutral(driver_neutral)
        elif self.motion == "relative" or self.full_frame:
            self.engine = Reenactor(self.renderer, driver_neutral, self.motion, feather=self.feather,
                                    match_colour=self.match_colour, full_frame=self.full_frame)
        self.background = background
        if self.engine is not None:
            self.engine.background = background

    def frames(self, landmarks: np.ndarray, rendered: np.ndarray | None = None,
               latencies: list | None = None) -> Iterator[np.ndarray]:
        """uint8 (H, W, 3) frames for (T, P, 2) driver landmarks, one per row (the background
        where a row is NaN); ``rendered`` (T, P, 2) receives the avatar landmarks of each frame,
        ``latencies`` (model s, frame s) per frame."""
        if self.background is None:
            raise FacesynthError("AvatarPipeline: start() it with the driver's neutral and a background first")
        if self.engine is not None:
            return reenact_frames(self.engine, landmarks, rendered, latencies)
        if rendered is not None:
            rendered[:] = landmarks
        return render_frames(self.renderer, landmarks, self.background,
                             STILL_FEATHER if self.feather is None else self.feather, latencies)
