"""Reenactment in the torch-free runtime: drive an avatar model with another face's
landmarks, frame by frame (no look-ahead), into the avatar's own frame.

    from facesynth.runtime import Reenactor
    r = Reenactor("avatar.onnx")                      # avatar neutral, shape PCA, frame: from the metadata
    for lm in driver_landmarks:                       # (P, 2) frame pixels (the model's scheme), one at a time
        frame, avatar_lm = r.step(lm)                 # uint8 (H, W, 3), float32 (P, 2)

The driver's neutral is given (``driver_neutral``), or taken from the first
``neutral_frames`` frames (ERI's rule, :func:`facesynth.neutral.select_neutral`; before
that many frames have arrived, from the frames seen so far). Retargeting is
:class:`facesynth.retarget.Retargeter`; the avatar's own frame is warped so that its whole
head follows the face (:class:`facesynth.runtime.fullframe.FrameWarp`), and the rendered
face is composited into that warped frame (:func:`facesynth.compositing.blend_face`).
"""

from __future__ import annotations

import base64
import time

import cv2
import numpy as np

from facesynth.compositing import GREY, blend_rendered
from facesynth.errors import FacesynthError
from facesynth.neutral import NEUTRAL_FRAMES, OnlineNeutral, select_neutral, typical_eyes
from facesynth.retarget import MOTIONS, Retargeter, ShapeSpace, retarget_scheme
from facesynth.runtime.fullframe import RING_SCALE, FrameWarp, checked_ring_scale
from facesynth.runtime.renderer import Renderer


class Avatar:
    """What the model's metadata says about its own face (:mod:`facesynth.onnx.avatar`).

    neutral : float64 (P, 2) or None (P of the model's scheme); shape_space : ShapeSpace or None;
    background : uint8 (H, W, 3) RGB or None (its neutral frame); frame_motion : float64
    (K - 68, 2) or None, the full-frame warp's learned motion coefficients, and ring_scale,
    the size of its head ring (:class:`FrameWarp`; ``RING_SCALE`` without ``frame_motion``).
    """

    def __init__(self, metadata: dict, where: str = "model"):
        self.where = where
        self.scheme = str(metadata.get("landmark_scheme", "ibug68"))
        n = metadata.get("avatar_neutral")
        self.neutral = None if n is None else np.asarray(n, np.float64)
        if self.neutral is not None:
            p = retarget_scheme(self.scheme).n_points
            if self.neutral.shape != (p, 2):
                raise FacesynthError(f"{where}: avatar_neutral metadata has shape {self.neutral.shape}, expected ({p}, 2)")
        pca = metadata.get("shape_pca")
        self.shape_space = None if pca is None else ShapeSpace.from_dict(pca, self.scheme)
        self._jpeg = metadata.get("background_jpeg")
        self._background = None
        motion = metadata.get("frame_motion")
        self.frame_motion = None if motion is None else _frame_motion(motion, where)
        # frame_motion.ring_scale: RING_SCALE in models exported before it was chosen per avatar
        self.ring_scale = RING_SCALE if motion is None else \
            checked_ring_scale(motion.get("ring_scale", RING_SCALE), f"{where}: frame_motion.ring_scale")

    @property
    def background(self) -> np.ndarray | None:
        if self._background is None and self._jpeg:
            buf = np.frombuffer(base64.b64decode(self._jpeg), np.uint8)
            img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
            if img is None:
                raise FacesynthError(f"{self.where}: background_jpeg metadata is not a readable JPEG")
            self._background = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        return self._background

    def frame_warp(self, method: str = "affine") -> FrameWarp:
        """The full-frame warp of the avatar's neutral frame with its learned motion and ring
        size (:class:`FrameWarp`; the prior where the metadata has none)."""
        return FrameWarp(self.background, self.require_neutral(), method, self.frame_motion, self.ring_scale)

    def missing(self, motion: str, full_frame: bool) -> list[str]:
        """What a file exported by an older version lacks for rendering with ``motion``
        ("relative": the retargeting's bounds) and ``full_frame`` (the learned warp): names
        for the app's one-line warning, [] for a current export."""
        out = []
        space = self.shape_space
        if motion == "relative" and space is not None:
            for value, name in ((space.eye_open_max, "the eye cap"), (space.residual_max, "the residual cap"),
                                (space.shift_range, "the head's travel bound"),
                                (space.param_norm_max, "the expressions' bound")):
                if value is None:
                    out.append(name)
        if full_frame and self.frame_motion is None:
            out.append("the learned full-frame warp")
        return out

    def require_neutral(self) -> np.ndarray:
        if self.neutral is None:
            raise FacesynthError(f"{self.where}: no avatar_neutral in the metadata (exported before reenactment "
                                 "support, or without the run's data): re-export it, or use --motion absolute")
        return self.neutral


def _frame_motion(entry, where: str) -> np.ndarray:
    try:
        m = np.asarray(entry["coefficients"], np.float64)
    except (TypeError, KeyError, ValueError) as exc:
        raise FacesynthError(f"{where}: frame_motion metadata needs a list of [share, parallax] coefficients") from exc
    if m.ndim != 2 or m.shape[1] != 2 or not np.isfinite(m).all():
        raise FacesynthError(f"{where}: frame_motion.coefficients must be finite (K, 2), got shape {m.shape}")
    return m


class Reenactor:
    """Driver landmarks -> avatar frames, one at a time.

    Parameters
    ----------
    model : path or Renderer
    driver_neutral : (P, 2) the driver's neutral face, optional (see the module docstring)
    motion : "relative" (default: the driver's motion on the avatar's own face) or "absolute"
        (the driver's landmarks as they are, the behaviour without retargeting)
    neutral_frames : frames collected to choose the driver's neutral when none is given
    background : uint8 (H, W, 3), optional; default the avatar's own frame from the
        metadata, else grey of the driver's landmark extent
    feather : soft edge in the rendered crop's pixels (default: 4% of the face,
        :func:`facesynth.compositing.blend_face`), match_colour : seam colour matching
    full_frame : warp the avatar's own frame so that the whole head follows the face, and
        composite into that (default: when no ``background`` is given and the metadata has the
        avatar's neutral and frame); False pastes the face into the still ``background``
    warp : the full-frame warp's interpolant, "affine" (default) or "tps" (:class:`FrameWarp`)
    """

    def __init__(self, model, driver_neutral=None, motion: str = "relative", neutral_frames: int = NEUTRAL_FRAMES,
                 background: np.ndarray | None = None, feather: float | None = None, match_colour: bool = True,
                 threads: int = 1, full_frame: bool | None = None, warp: str = "affine"):
        if motion not in MOTIONS:
            raise FacesynthError(f"motion must be one of {MOTIONS}, got {motion!r}")
        online = OnlineNeutral(neutral_frames)  # checks neutral_frames, before the model is loaded
        self.renderer = model if isinstance(model, Renderer) else Renderer(model, threads=threads)
        self.avatar = Avatar(self.renderer.metadata, str(self.renderer.path))
        self.motion = motion
        self.neutral_frames = int(neutral_frames)
        self.feather, self.match_colour = feather, match_colour
        self._online = online if driver_neutral is None else None  # choosing the driver's neutral
        self._retarget: Retargeter | None = None
        self.last_model_s = 0.0  # seconds of the last model call
        if motion == "relative":
            self.avatar.require_neutral()
        if driver_neutral is not None:
            self._set_neutral(self.renderer.validate(driver_neutral)[0])
        self.background = background if background is not None else self.avatar.background
        own = self.avatar.neutral is not None and self.avatar.background is not None
        if full_frame is None:
            full_frame = background is None and own
        if full_frame and not own:
            raise FacesynthError(f"{self.avatar.where}: a full-frame warp needs the avatar's neutral and frame in the "
                                 "metadata (re-export the model)")
        self.full_frame = bool(full_frame)
        self.frame_warp = self.avatar.frame_warp(warp) if self.full_frame else None

    def _set_neutral(self, neutral: np.ndarray) -> None:
        self.driver_neutral = np.asarray(neutral, np.float64)
        if self.motion == "relative":
            self._retarget = Retargeter(self.avatar.neutral, self.driver_neutral, self.avatar.shape_space, "relative",
                                        scheme=self.avatar.scheme)

    def retarget(self, landmarks) -> np.ndarray:
        """One driver frame (P, 2) -> float32 (P, 2) avatar landmarks in the avatar's frame."""
        lm = self.renderer.validate(landmarks)
        if len(lm) != 1:
            raise FacesynthError(f"Reenactor: one face at a time, got a batch of {len(lm)}")
        lm = lm[0]
        if self.motion == "absolute":
            return lm
        if self._online is not None and self._online.choosing:  # no neutral given: chosen online
            self._set_neutral(self._online.see(lm))
        return self._retarget.one(lm.astype(np.float64)).astype(np.float32)

    def step(self, landmarks) -> tuple[np.ndarray, np.ndarray]:
        """One driver frame -> (uint8 (H, W, 3) frame, float32 (P, 2) avatar landmarks)."""
        avatar_lm = self.retarget(landmarks)
        t0 = time.perf_counter()
        crops, masks, placements = self.renderer.render(avatar_lm[None])
        self.last_model_s = time.perf_counter() - t0
        bg = self.frame_warp(avatar_lm) if self.full_frame else self.background
        if bg is None:
            w, h = (int(np.ceil(v)) + 32 for v in avatar_lm.max(0))
            bg = self.background = np.full((h, w, 3), GREY, np.uint8)
        frame = blend_rendered(crops, masks, placements, bg, 0, self.feather, self.match_colour)
        return frame, avatar_lm


def driver_neutral_of(landmarks: np.ndarray, index: int | None = None) -> tuple[np.ndarray, int]:
    """The driver's neutral (P, 2) and its row: row ``index`` as it is (``--driver-neutral N``),
    or :func:`facesynth.neutral.select_neutral` over the whole clip (a file driver) with its
    eyes where the clip's usually are (:func:`facesynth.neutral.typical_eyes`, as the avatar's)."""
    lm = np.asarray(landmarks, np.float64)
    chosen = index is None
    if chosen:
        index = select_neutral(lm)[0]
    if not -len(lm) <= int(index) < len(lm):
        raise FacesynthError(f"--driver-neutral: row {index} out of range for {len(lm)} driver frames")
    row = lm[int(index)]
    if not np.isfinite(row).all():
        raise FacesynthError(f"--driver-neutral: driver row {index} has no face (NaN)")
    return (typical_eyes(row, lm) if chosen else row), int(index) % len(lm)


def reenact_frames(reenactor: Reenactor, landmarks: np.ndarray, rendered: np.ndarray | None = None,
                   latencies: list | None = None):
    """uint8 (H, W, 3) frames of ``reenactor`` for (T, P, 2) driver landmarks, one per row
    (the background where a row is NaN). ``rendered`` (T, P, 2), if given, receives the
    avatar landmarks of each frame; ``latencies`` collects (model s, frame s) per frame."""
    for i, lm in enumerate(landmarks):
        t0 = time.perf_counter()
        if not np.isfinite(lm).all():
            yield reenactor.background.copy()
            continue
        frame, avatar_lm = reenactor.step(lm)
        if rendered is not None:
            rendered[i] = avatar_lm
        if latencies is not None:
            latencies.append((reenactor.last_model_s, time.perf_counter() - t0))
        yield frame
