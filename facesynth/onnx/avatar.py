"""What a landmark-driven model needs to be driven by *another* face, written
into its ONNX metadata at export time (torch-side; the runtime reads it with
:func:`facesynth.runtime.reenact.avatar_from_metadata`):

* ``avatar_neutral``: the avatar's neutral landmarks (P, 2) in its frame pixels, chosen
  among the training frames by ERI's rule (:func:`facesynth.neutral.select_neutral`), its
  eyes put where the training frames' usually are (:func:`facesynth.neutral.typical_eyes`),
  and ``avatar_neutral_row`` (the frame's index in the clip);
* ``shape_pca``: the model's shape PCA (mean, orthonormal components, clamp limits
  k sqrt(lambda)), the widest opening of each eye over the training frames
  (``eye_open_max``, :func:`facesynth.landmarks.eye_openings`), the largest norm of
  their part outside the components (``residual_max``) and of their clamped parameters in
  units of the limits (``param_norm_max``), for
  :class:`facesynth.shape_space.ShapeSpace`;
* ``background_jpeg``: that neutral frame, JPEG (quality 90) in base64, the avatar's own
  frame the app composites into, and ``frame_size`` [W, H];
* ``frame_motion``: how the full-frame warp's control points besides the landmarks follow
  the face, learned from up to ``headmotion.FRAMES`` training frames, and the size of the
  head's ring, chosen on ``headmotion.VALIDATION`` others
  (:func:`facesynth.onnx.headmotion.fit_frame_motion`: ``coefficients`` (K - 68, 2),
  ``frames``, ``lambda``, ``points_fitted``, ``ring_scale``, ``ring_scores``,
  ``validation_frames``);
* ``coverage_recording`` (478-point avatars): the training frames as the studio's coverage
  meter reads them (:func:`facesynth.coverage.recording_entry`), for the page's live reach.
"""

from __future__ import annotations

import base64
import dataclasses
import logging

import cv2
import numpy as np

from facesynth.coverage import RECORDING_KEY, recording_entry
from facesynth.errors import FacesynthError
from facesynth.landmarks import eye_openings
from facesynth.neutral import select_neutral, typical_eyes
from facesynth.onnx.headmotion import FRAMES, VALIDATION, fit_frame_motion
from facesynth.retarget import RETARGET_SCHEMES, ShapeSpace, head_shifts, retarget_scheme

log = logging.getLogger(__name__)
JPEG_QUALITY = 90


def encode_jpeg(image: np.ndarray) -> str:
    """uint8 RGB (H, W, 3) -> base64 JPEG text."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise FacesynthError("could not JPEG-encode the avatar's background frame")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def shape_space(syn, landmarks: np.ndarray | None = None, neutral: np.ndarray | None = None) -> ShapeSpace:
    """The synthesizer's shape PCA (its :class:`ShapeEncoder` buffers) as a ShapeSpace; with
    the training frames' ``landmarks`` (N, P, 2), each eye's opening capped at the widest of
    them (``eye_open_max``) and the part of a shape the components do not span at the
    largest of theirs (``residual_max``), and the components' parameters within the largest
    norm of theirs (``param_norm_max``); with the avatar's ``neutral`` (P, 2) too, how far
    they move the head from it (``shift_range``, :func:`facesynth.retarget.head_shifts`)."""
    enc = syn.encoder
    scheme = getattr(syn, "scheme", "ibug68")
    space = ShapeSpace(enc.mean.double().numpy(), enc.components.double().numpy(), enc.limit.double().numpy(),
                       scheme=scheme)
    if landmarks is None:
        return space
    lm = np.asarray(landmarks, np.float64)
    lm = lm[np.isfinite(lm).all((1, 2))]
    shifts = None if neutral is None else head_shifts(retarget_scheme(scheme), neutral, lm)
    residual, params = space.norms(lm)
    return dataclasses.replace(space, eye_open_max=eye_openings(lm, retarget_scheme(scheme)).max(0),
                               residual_max=float(residual.max()), param_norm_max=float(params.max()),
                               shift_range=None if shifts is None else np.stack([shifts.min(0), shifts.max(0)]))


def avatar_metadata(syn, landmarks: np.ndarray, rows: np.ndarray | None = None, sequence=None) -> dict:
    """Metadata entries for reenactment: the neutral among ``landmarks`` (N, P, 2) (the
    training frames; ``rows`` their indices in ``sequence``), the shape PCA and, when
    ``sequence`` has frames, the neutral frame as background; for 478-point (MediaPipe)
    landmarks, the training frames as the coverage meter reads them, kept at its frame rate
    when ``sequence`` gives their times."""
    lm = np.asarray(landmarks, np.float32)
    idx, info = select_neutral(lm)
    row = int(rows[idx]) if rows is not None else idx
    neutral = np.round(typical_eyes(lm[idx], lm), 3)  # the eyes where the clip's usually are
    meta = {"avatar_neutral": neutral.tolist(), "avatar_neutral_row": row,
            "avatar_neutral_rule": f"{info['rule']}; eyes typical", "shape_pca": shape_space(syn, lm, neutral).to_dict()}
    if sequence is not None and sequence.has_frames:
        frame = np.asarray(sequence.frame(row))
        meta["background_jpeg"] = encode_jpeg(frame)
        meta["frame_size"] = [int(frame.shape[1]), int(frame.shape[0])]
        meta["frame_motion"] = frame_motion(frame, neutral, lm, rows, sequence)
    if lm.shape[1] == 478 and getattr(syn, "scheme", "ibug68") == "mediapipe478":
        times = None
        if sequence is not None and sequence.fps:
            times = np.asarray(sequence.frame_index)[np.arange(len(lm)) if rows is None else np.asarray(rows)] / float(sequence.fps)
        entry = recording_entry(lm, meta["avatar_neutral"], times)
        if entry is not None:
            meta[RECORDING_KEY] = entry
    return meta


def frame_motion(frame: np.ndarray, neutral: np.ndarray, landmarks: np.ndarray, rows, sequence) -> dict:
    """The ``frame_motion`` entry: :func:`fit_frame_motion` of the warp of ``frame`` (the
    neutral frame, landmarks ``neutral`` (P, 2)), its motion fitted on up to ``FRAMES`` of the
    training frames (``landmarks`` (N, P, 2), ``rows`` their indices in ``sequence``), evenly
    spaced, and its ring's size chosen on ``VALIDATION`` others, halfway between them (on
    the fit's own frames when there are no others)."""
    n = len(landmarks)
    pick = np.unique(np.linspace(0, n - 1, min(FRAMES, n)).round().astype(int))
    halves = (pick[:-1] + pick[1:]) // 2
    halves = halves[halves > pick[:-1]]  # a training frame between two of the fit's
    if not len(halves):  # a short clip: the fit has read every training frame
        halves = pick
    halves = halves[np.unique(np.linspace(0, len(halves) - 1, min(VALIDATION, len(halves))).round().astype(int))]

    def frames(idx):
        return (np.asarray(f) for f in sequence.iter_frames([int(rows[i]) if rows is not None else int(i) for i in idx]))

    fw, info = fit_frame_motion(frame, neutral, frames(pick), landmarks[pick], frames(halves), landmarks[halves])
    return {"coefficients": np.round(fw.motion, 4).tolist(), **info}


def run_avatar_metadata(run_dir, syn) -> dict:
    """:func:`avatar_metadata` of a ``train.py`` run (its data and training rows); {} with a
    log line when the run's data cannot be reloaded (the model then needs --driver-neutral
    style inputs: the runtime says so)."""
    from facesynth.rundir import read_config, run_data

    if getattr(syn, "scheme", "ibug68") not in RETARGET_SCHEMES:
        log.info("no reenactment metadata: retargeting takes %s landmarks, this model takes %s",
                 " or ".join(RETARGET_SCHEMES), syn.scheme)
        return {}
    try:
        seq, rows, _ = run_data(read_config(run_dir))
    except FacesynthError as exc:
        log.warning("no reenactment metadata (avatar neutral, background): %s", exc)
        return {}
    return avatar_metadata(syn, seq.landmarks[rows], rows, seq)
