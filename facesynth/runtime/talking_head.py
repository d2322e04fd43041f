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

A file is checked before it is accepted (:func:`check_talking_head_file`, which every
``TalkingHead`` runs on loading): its metadata (:data:`facesynth.contract.TALKING_HEAD_METADATA_KEYS`),
its graph's inputs and outputs against :data:`facesynth.contract.TALKING_HEAD_SIGNATURE`, and a
first run on the avatar's own neutral: finite landmarks equal to that neutral, a frame of the
file's size, and that frame like the avatar's own neutral frame over the face
(:data:`FIRST_RUN_MIN_PSNR`). A corrupt or hand-made file is one FacesynthError naming it,
never an ONNX Runtime traceback at the first driver frame.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from facesynth.contract import (
    TALKING_HEAD_FORMAT,
    TALKING_HEAD_INPUTS,
    TALKING_HEAD_METADATA_KEYS,
    TALKING_HEAD_SIGNATURE,
)
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.metrics import psnr
from facesynth.neutral import NEUTRAL_FRAMES, OnlineNeutral
from facesynth.runtime.checks import check_coordinate_range, check_face_extent, check_metadata_size, check_outputs
from facesynth.runtime.reenact import Avatar
from facesynth.runtime.renderer import _decode, _session, check_batch

# The first run's frame against the avatar's own neutral frame, PSNR over the box of its neutral
# landmarks: good files give 28.6-35.1 dB (lp_d13, lp_d3, the built-in synthetic subject). 64 KiB of
# random bytes written into the middle of each large float weight of four such files: 2 of 22 fail to
# run, 19 of the other 20 render at 5.2-16.4 dB, one at 20.4 dB. (Overwritten int8 basis codes can
# leave the neutral face as it was: only a driven frame shows them; not caught here.)
FIRST_RUN_MIN_PSNR = 20.0
_ORT_TYPES = {"tensor(float)": "float32", "tensor(uint8)": "uint8", "tensor(double)": "float64",
              "tensor(int64)": "int64", "tensor(int32)": "int32"}


def check_talking_head_file(path: str | os.PathLike) -> dict:
    """The metadata of the talking-head file ``path`` once it is checked (metadata, the graph's
    inputs and outputs against the contract, a first run on the avatar's own neutral: see the
    module docstring); FacesynthError naming the file otherwise. Torch-free: ``facesynth app``,
    ``facesynth web build`` and ``facesynth serve`` accept a file through it."""
    return TalkingHead(path).metadata


def _check_metadata(meta: dict, where: str) -> tuple[int, tuple[int, int], float]:
    """(P, (W, H), feather) of a talking-head file's metadata; FacesynthError naming the key."""
    missing = [k for k in TALKING_HEAD_METADATA_KEYS if k not in meta]
    if missing:
        raise FacesynthError(f"{where}: a talking-head file without the metadata {', '.join(missing)} (written by "
                             "'facesynth export RUN --talking-head'? edited or cut short?)")
    scheme = get_scheme(str(meta["landmark_scheme"])) if isinstance(meta["landmark_scheme"], str) else None
    if scheme is None or meta["n_landmarks"] != scheme.n_points:
        raise FacesynthError(f"{where}: metadata 'n_landmarks' {meta['n_landmarks']!r} and 'landmark_scheme' "
                             f"{meta['landmark_scheme']!r} disagree")
    size = meta["frame_size"]
    h, w = check_metadata_size(size[::-1] if isinstance(size, list) else size, where, "frame_size")
    feather = meta["feather"]
    if isinstance(feather, bool) or not isinstance(feather, (int, float)) or not 0 <= feather < max(w, h):
        raise FacesynthError(f"{where}: metadata 'feather' is {feather!r}, expected pixels >= 0")
    return scheme.n_points, (w, h), float(feather)


def _check_graph(session: ort.InferenceSession, where: str, n_points: int) -> None:
    """The graph's inputs and outputs, in order, against :data:`TALKING_HEAD_SIGNATURE`."""
    for kind, args in (("inputs", session.get_inputs()), ("outputs", session.get_outputs())):
        want = TALKING_HEAD_SIGNATURE[kind]
        if [a.name for a in args] != list(want):
            raise FacesynthError(f"{where}: graph {kind} {[a.name for a in args]}, a talking head has {list(want)}")
        for a in args:
            dtype, rank = want[a.name]
            if _ORT_TYPES.get(a.type, a.type) != dtype or len(a.shape) != rank:
                raise FacesynthError(f"{where}: graph {kind[:-1]} {a.name!r} is {_ORT_TYPES.get(a.type, a.type)} of rank "
                                     f"{len(a.shape)}, a talking head's is {dtype} of rank {rank}")
    points = {a.name: a.shape[-2] for a in session.get_inputs()}
    if any(isinstance(p, int) and p != n_points for p in points.values()):
        raise FacesynthError(f"{where}: graph inputs of {points} points, the metadata says {n_points}")


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
        where = str(self.path)
        if self.metadata.get("format") != TALKING_HEAD_FORMAT:
            raise FacesynthError(f"{self.path}: not a talking-head graph (format {self.metadata.get('format')!r}, "
                                 f"expected {TALKING_HEAD_FORMAT!r})")
        self.n_points, self.frame_size, self.feather = _check_metadata(self.metadata, where)  # frame_size (W, H)
        _check_graph(self.session, where, self.n_points)
        self.avatar = Avatar(self.metadata, where)
        self.scheme = self.avatar.scheme  # the landmark scheme's name, as the metadata gives it
        self.background = self.avatar.background  # uint8 (H, W, 3) its neutral frame: shown where a driver has no face
        if self.background is None or self.background.shape[:2] != self.frame_size[::-1]:
            raise FacesynthError(f"{where}: metadata 'background_jpeg' is not a {self.frame_size[0]}x{self.frame_size[1]} "
                                 "frame (the file's frame_size)")
        self.last_model_s = 0.0  # seconds of the last ONNX Runtime call
        self._first_run()
        self.neutral_frames = int(neutral_frames)
        online = OnlineNeutral(neutral_frames)  # checks neutral_frames either way
        self._online = online if driver_neutral is None else None  # choosing the driver's neutral
        self.driver_neutral = None
        if driver_neutral is not None:
            self.use_neutral(driver_neutral)

    def _first_run(self) -> None:
        """Run the graph on the avatar's own neutral (as the driver and its neutral): the
        landmarks must come back as that neutral, the frame be the file's size and, over the
        face, like the avatar's own neutral frame (:data:`FIRST_RUN_MIN_PSNR`)."""
        where = str(self.path)
        n = np.ascontiguousarray(self.avatar.require_neutral(), np.float32)
        options = ort.RunOptions()
        options.log_severity_level = 4  # the failure is reported below, in one line
        try:
            frame, lm = self.session.run(None, dict(zip(TALKING_HEAD_INPUTS, (n[None], n), strict=True)), options)
        except Exception as exc:  # onnxruntime raises several types for a graph that cannot run
            raise FacesynthError(f"{where}: the graph fails on the avatar's own neutral, a corrupt file? "
                                 f"({' '.join(str(exc).split())[:200]})") from None
        w, h = self.frame_size
        if frame.shape != (1, h, w, 3) or frame.dtype != np.uint8 or lm.shape != (1, self.n_points, 2):
            raise FacesynthError(f"{where}: on the avatar's own neutral the graph gives a frame {frame.dtype} "
                                 f"{frame.shape} and landmarks {lm.shape}, expected uint8 (1, {h}, {w}, 3) and "
                                 f"(1, {self.n_points}, 2)")
        check_outputs(where, avatar_landmarks=lm)
        if np.abs(lm[0] - n).max() > 0.5:
            raise FacesynthError(f"{where}: driven by its own neutral, the avatar's landmarks move by "
                                 f"{np.abs(lm[0] - n).max():.3g} px (expected its neutral): a corrupt file?")
        lo = np.clip(np.floor(n.min(0)).astype(int), 0, [w - 1, h - 1])
        hi = np.clip(np.ceil(n.max(0)).astype(int), 0, [w - 1, h - 1])
        face = np.zeros((h, w), bool)
        face[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1] = True
        got = psnr(frame[0], self.background, face)
        if got < FIRST_RUN_MIN_PSNR:
            raise FacesynthError(f"{where}: driven by its own neutral, the face it renders is {got:.1f} dB from its own "
                                 f"neutral frame (a good file: over {FIRST_RUN_MIN_PSNR:g} dB): corrupt weights?")

    def use_neutral(self, driver_neutral) -> "TalkingHead":
        """Take (P, 2) ``driver_neutral`` as the driver's neutral from now on; returns self."""
        self.driver_neutral = self._points(np.asarray(driver_neutral)[None], "driver_neutral")[0]
        self._online = None  # given: no longer chosen online
        return self

    def _points(self, values, field: str) -> np.ndarray:
        x = check_batch(values, field, (self.n_points, 2), "frame pixels", f"(B, {self.n_points}, 2)",
                        " (a frame without a face)")
        check_coordinate_range(x, field)
        check_face_extent(x, field)
        return x

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
        if self._online is not None and self._online.choosing:  # no neutral given: chosen online
            self.driver_neutral = self._online.see(lm[0])
        frames, avatar = self.run(lm)
        return frames[0], avatar[0]
