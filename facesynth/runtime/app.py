"""``facesynth app``: render a talking-head video from landmarks with an exported model.

    facesynth app --model model.onnx (--landmarks L.npy | --video DRIVER.mp4) --out out.mp4
                  [--motion relative|absolute] [--driver-neutral N] [--save-landmarks L.npy]
                  [--background IMG] [--side-by-side] [--smooth] [--size WxH]

Each frame's landmarks are retargeted onto the avatar (``--motion relative``, the default:
the driver's expression and head motion relative to its neutral, on the avatar's own face;
:class:`facesynth.runtime.reenact.Reenactor`) and drive the model (batch 1, as a live app
would); the face is composited into the avatar's own frame (the model's metadata) with a
feathered, colour-matched seam (:func:`facesynth.runtime.blend.blend_face`), and the video is
written atomically (mp4v) at the driver's own frame rate. A progress bar shows frames/s; the
summary gives latency percentiles of the model call and of the whole frame. Torch is never
imported.

Every output path is checked, and refused when it is one of the inputs, before the model is
loaded; the video is reopened and checked before it is kept
(:func:`facesynth.videofile.atomic_video`), and all outputs are renamed into place together.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from facesynth.errors import FacesynthError
from facesynth.imaging import composite
from facesynth.io import atomic_path, check_writable, refuse_overwriting_inputs
from facesynth.progress import bar, stage
from facesynth.runtime.checks import check_coordinate_range, check_frame_size, check_in_frame
from facesynth.runtime.video import (
    contact_sheet,
    detect_video_landmarks,
    draw_landmarks,
    fit_into,
    write_image,
)
from facesynth.videofile import atomic_video

log = logging.getLogger(__name__)
GREY = 128
SHEET_DIR = Path("/tmp/facesynth_out")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="ONNX model written by 'facesynth export'")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--landmarks", help="driving landmarks (T, P, 2) in the model's scheme (mediapipe478 ones are mapped "
                                         "for a 68-point model): .npy, a clip folder, or any readable sequence")
    src.add_argument("--video", help="driving video; landmarks are detected in the model's scheme: dlib (the 'ingest' extra), "
                                     "MediaPipe (the 'mediapipe' extra) or both (ibug68+iris)")
    p.add_argument("--driver-video", help="with --landmarks: the video they came from, shown left in --side-by-side "
                                             "(default for an ingest folder: the video its meta.json names)")
    p.add_argument("--out", required=True, help="output video (.mp4, mp4v codec)")
    p.add_argument("--background", help="background image (default: the avatar's own frame from the model, else grey)")
    p.add_argument("--motion", choices=("relative", "absolute"),
                   help="relative (default for models exported with their avatar metadata): the driver's motion on the avatar's own "
                        "face, in the avatar's frame; absolute (default otherwise): the driver's landmarks as they are, on grey")
    p.add_argument("--driver-neutral", type=int, help="driver row used as its neutral face (default: chosen automatically)")
    p.add_argument("--save-landmarks", help="write the float32 (T, P, 2) avatar landmarks rendered, one row per driver frame (.npy)")
    p.add_argument("--size", help="output frame size WxH when no background is given (default: the landmarks' extent)")
    p.add_argument("--side-by-side", action="store_true", help="driver (video frame or drawn landmarks) left, rendering right")
    p.add_argument("--smooth", action="store_true", help="One Euro filter on the landmarks (Casiez et al. 2012)")
    p.add_argument("--min-cutoff", type=float, default=1.0, help="One Euro min cutoff, Hz (default 1.0)")
    p.add_argument("--beta", type=float, default=0.05, help="One Euro speed coefficient (default 0.05)")
    p.add_argument("--fps", type=float, help="output frame rate (default: the driver's own: an ingest folder's meta.json, "
                                         "else the driver video's; 30 when neither records one)")
    p.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads (default 1)")
    p.add_argument("--feather", type=float, help="soft edge of the pasted face: pixels of the rendered crop in the avatar's "
                                                 "own frame (default 4%% of the face), frame pixels on --background (default 2)")
    p.add_argument("--no-colour-match", action="store_true", help="do not match the face's colour to the frame at the seam")
    p.add_argument("--max-frames", type=int, help="render only the first N frames (N >= 1)")
    p.add_argument("--contact-sheet", help=f"also write a PNG contact sheet (driver above rendering), e.g. {SHEET_DIR}/sheet.png")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


# ------------------------------------------------------------------ inputs
def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise FacesynthError(f"--size: expected WxH (e.g. 480x480), got {text!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise FacesynthError(f"--size: width and height must be in [16, 8192], got {w}x{h}")
    return w, h


def default_size(landmarks: np.ndarray, margin: float = 0.25) -> tuple[int, int]:
    """(W, H) covering every landmark plus a margin of the face size; even numbers (codecs)."""
    finite = landmarks[np.isfinite(landmarks).all(axis=(1, 2))]
    if not len(finite):
        raise FacesynthError("landmarks: no frame has a face (all rows NaN)")
    hi = finite.reshape(-1, 2).max(0)
    lo = finite.reshape(-1, 2).min(0)
    pad = margin * float((hi - lo).max())
    check_coordinate_range(finite)
    w, h = (int(np.ceil(v + pad)) for v in hi)
    return check_frame_size((max(w + w % 2, 64), max(h + h % 2, 64)), "landmarks (the frame size they imply)")


def load_background(path: str | None, size: tuple[int, int]) -> np.ndarray:
    """uint8 RGB (H, W, 3): an image file, or neutral grey of ``size`` (W, H)."""
    if path is None:
        w, h = size
        return np.full((h, w, 3), GREY, np.uint8)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FacesynthError(f"{path}: not a readable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# ----------------------------------------------------------------- rendering
def render_frames(renderer, landmarks: np.ndarray, background: np.ndarray, feather: float = 2.0,
                  latencies: list | None = None) -> Iterator[np.ndarray]:
    """uint8 (H, W, 3) frames, one per landmark row (the background where a row is NaN).

    ``latencies`` (a list) collects (model seconds, frame seconds) per rendered frame.
    """
    for lm in landmarks:
        t0 = time.perf_counter()
        if not np.isfinite(lm).all():
            frame = background.copy()
            t1 = time.perf_counter()
        else:
            crops, masks, placements = renderer.render(lm[None])
            t1 = time.perf_counter()
            crop = np.ascontiguousarray(crops[0].transpose(1, 2, 0))
            if crop.shape[2] == 1:
                crop = np.repeat(crop, 3, axis=2)
            frame = composite(crop, masks[0, 0], placements[0].astype(np.float64), background, feather)
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


# ------------------------------------------------------------------ checks
def check_options(args: argparse.Namespace) -> list[str]:
    """The numeric options and every output path, before any file is read; returns the outputs."""
    if args.fps is not None and not 0 < args.fps < 1e4:
        raise FacesynthError(f"--fps: expected a frame rate > 0 (frames per second), got {args.fps:g}")
    if args.max_frames is not None and args.max_frames < 1:
        raise FacesynthError(f"--max-frames: expected a number of frames >= 1, got {args.max_frames}")
    if args.save_landmarks and Path(args.save_landmarks).suffix != ".npy":
        raise FacesynthError(f"--save-landmarks: expected a .npy path, got {args.save_landmarks}")
    if args.contact_sheet and not cv2.haveImageWriter(str(args.contact_sheet)):
        raise FacesynthError(f"--contact-sheet: no image format for {args.contact_sheet} (use .png or .jpg)")
    outputs = [p for p in (args.out, args.contact_sheet, args.save_landmarks) if p]
    for path in outputs:
        check_writable(path)
    if len({os.path.realpath(p) for p in outputs}) < len(outputs):
        raise FacesynthError(f"--out, --contact-sheet and --save-landmarks name the same file: {' '.join(outputs)}")
    return outputs


def check_faces(landmarks: np.ndarray, where: str, max_frames: int | None) -> None:
    """FacesynthError naming ``where`` when the driver has no frame, or no frame with a face."""
    if not len(landmarks):
        raise FacesynthError(f"{where}: holds no frames (0 landmark rows), nothing to render")
    if not np.isfinite(landmarks).all(axis=(1, 2)).any():
        rows = f"the first {len(landmarks)} rows (--max-frames)" if max_frames else f"all {len(landmarks)} rows"
        raise FacesynthError(f"{where}: no frame has a face ({rows} are NaN), nothing to render")


def detect_with_progress(driver, max_frames: int | None, scheme: str, enabled: bool) -> np.ndarray:
    """:func:`facesynth.runtime.video.detect_video_landmarks` on the first ``max_frames``
    frames of ``driver`` (:class:`facesynth.data.frames.VideoFrames`, decoded as they are
    needed) with a progress bar and a stage line (both off under --quiet); FacesynthError
    naming the video when it has no frame, or no frame with a face."""
    passes = 2 if scheme == "ibug68+iris" else 1
    total = min(len(driver), max_frames or len(driver)) or None
    with stage("landmark detection") as st, bar(total=total and passes * total, unit="frame", desc="landmarks",
                                                  enabled=enabled) as b:
        landmarks = detect_video_landmarks(lambda: itertools.islice(driver.iter_all(), max_frames), scheme,
                                           on_frame=lambda i, source: b.update(1))
        found = int(np.isfinite(landmarks).all(axis=(1, 2)).sum())
        st.set(f"{found} of {len(landmarks)} frames of {driver.path} with a face")
    if not len(landmarks):
        raise FacesynthError(f"{driver.path}: no frames decoded, nothing to render")
    if not found:
        raise FacesynthError(f"{driver.path}: no face found in any of its {len(landmarks)} frames, nothing to render")
    return landmarks


def talking_head(args: argparse.Namespace):
    """A :class:`facesynth.runtime.talking_head.TalkingHead` when ``--model`` is a talking-head
    file (``facesynth export RUN --talking-head``), else None; FacesynthError naming the
    options such a file fixes at export (its own frame, relative motion, its seam)."""
    from facesynth.contract import TALKING_HEAD_FORMAT
    from facesynth.runtime.renderer import read_metadata
    from facesynth.runtime.talking_head import TalkingHead

    if read_metadata(args.model).get("format") != TALKING_HEAD_FORMAT:
        return None
    fixed = [opt for opt, given in (("--background", args.background), ("--motion absolute", args.motion == "absolute"),
                                    ("--feather", args.feather is not None), ("--no-colour-match", args.no_colour_match),
                                    ("--size", args.size)) if given]
    if fixed:
        raise FacesynthError(f"{args.model} is a talking-head file (its frame, relative motion and seam are fixed at "
                             f"export): {', '.join(fixed)} cannot apply; export the face model for that "
                             "(facesynth export RUN --out M.onnx)")
    args.motion = "relative"
    return TalkingHead(args.model, threads=args.threads)


# ------------------------------------------------------------------ command
def run(args: argparse.Namespace) -> int:
    from facesynth.data.frames import VideoFrames
    from facesynth.data.readers import ingest_video, load_landmarks
    from facesynth.landmarks import get_scheme
    from facesynth.retarget import RETARGET_SCHEMES
    from facesynth.runtime.filters import smooth_landmarks
    from facesynth.runtime.reenact import Avatar, Reenactor, driver_neutral_of, reenact_frames
    from facesynth.runtime.renderer import Renderer

    outputs = check_options(args)  # before any decoding or rendering
    meta_fps = driver_video = None
    inputs = [args.model, args.background, args.video, args.landmarks, args.driver_video]
    if args.landmarks and Path(args.landmarks).is_dir():  # an ingest folder: its meta.json names the video and rate
        folder_video, meta_fps = ingest_video(args.landmarks)
        inputs += [Path(args.landmarks, "landmarks.npy"), Path(args.landmarks, "meta.json"), folder_video]
        # its video is opened when its frames are shown, or for its frame rate when meta.json has none
        driver_video = folder_video if args.side_by_side or args.contact_sheet or meta_fps is None else None
    driver_video = args.video or args.driver_video or driver_video
    refuse_overwriting_inputs(outputs, inputs)
    head = talking_head(args)  # a talking-head file renders whole frames; else a face model and the numpy pipeline
    renderer = None if head else Renderer(args.model, threads=args.threads)
    metadata = head.metadata if head else renderer.metadata
    scheme = head.scheme if head else renderer.scheme.name
    avatar = Avatar(metadata, args.model)
    if scheme not in RETARGET_SCHEMES and args.motion == "relative":
        raise FacesynthError(f"--motion relative: retargeting takes {' or '.join(RETARGET_SCHEMES)} landmarks, and "
                             f"{args.model} takes {scheme} ones; use --motion absolute (a driver in the same scheme)")
    if args.motion is None:
        args.motion = "relative" if avatar.neutral is not None else "absolute"
        if avatar.neutral is None:
            log.warning("%s has no avatar metadata (%s): --motion absolute", args.model,
                        "an older export" if scheme in RETARGET_SCHEMES else f"retargeting does not take {scheme} landmarks")
    if args.motion == "relative":
        avatar.require_neutral()
    driver = VideoFrames(driver_video) if driver_video else None  # decoded frame by frame, never held whole
    video_fps = driver.fps if driver is not None and 0 < driver.fps < 1e4 else None
    if args.video:
        landmarks = detect_with_progress(driver, args.max_frames, scheme, not args.no_progress)
    else:
        landmarks = load_landmarks(args.landmarks, scheme=scheme)  # mediapipe478 -> ibug68 is mapped; the reverse is an error
        if args.max_frames:
            landmarks = landmarks[: args.max_frames]
        check_faces(landmarks, args.landmarks, args.max_frames)
        if (args.side_by_side or args.contact_sheet) and driver is not None and 0 < len(driver) < len(landmarks):
            # the header's count, before any work; reading the frames checks the rest
            raise FacesynthError(f"{driver_video}: {len(driver)} frames for {len(landmarks)} landmark rows")
    fps = float(args.fps or meta_fps or video_fps or 30.0)
    if not (args.fps or meta_fps or video_fps):
        log.info("%s records no frame rate: %g fps (--fps sets it)", args.video or args.landmarks, fps)
    if args.smooth:
        landmarks = smooth_landmarks(landmarks, fps, args.min_cutoff, args.beta)
    neutral = None
    if args.motion == "relative" or args.driver_neutral is not None:
        neutral, neutral_row = driver_neutral_of(landmarks, args.driver_neutral)
    # the avatar's own frame, warped so that its whole head follows the face (either motion)
    full_frame = not args.background and avatar.neutral is not None and avatar.background is not None
    if head:
        reenactor = head.use_neutral(neutral)
    else:
        reenactor = Reenactor(renderer, neutral, args.motion, feather=args.feather, match_colour=not args.no_colour_match,
                              full_frame=full_frame)
    if args.background:
        background = load_background(args.background, (0, 0))
    elif full_frame:
        background = avatar.background
    elif driver is not None and not args.size:
        h, w = driver.size
        background = load_background(None, (w, h))
    else:
        background = load_background(None, parse_size(args.size) if args.size else default_size(landmarks))
    h, w = background.shape[:2]
    # before any rendering; the driver's points are in its own frame, when known
    driver_size = (w, h) if driver is None else driver.size[::-1]
    check_in_frame(landmarks, driver_size, args.landmarks or args.video)
    # without a driver video, its dots are drawn in its own frame (not on the avatar's face)
    dots_on = background if args.motion == "absolute" or driver is not None else \
        load_background(None, default_size(landmarks))
    out_w = 2 * w if args.side_by_side else w
    n = len(landmarks)
    latencies: list = []
    rendered = np.full((n, get_scheme(scheme).n_points, 2), np.nan, np.float32)  # the avatar landmarks of each frame (--save-landmarks)
    sheet_idx = set(np.linspace(0, n - 1, min(6, n)).round().astype(int).tolist()) if args.contact_sheet else set()
    sheet_top, sheet_bottom = [], []
    shown_left = set(range(n)) if args.side_by_side else sheet_idx  # the frames that need the driver's picture
    driver_iter = driver.read(sorted(shown_left)) if driver is not None else None
    out = Path(args.out)
    t_start = time.perf_counter()
    with contextlib.ExitStack() as written:  # every output is renamed into place only once all are written
        video = written.enter_context(atomic_video(out, fps, (out_w, h)))
        progress = bar(total=n, unit="frame", desc="app", enabled=not args.no_progress)
        reenactor.background = background
        if args.motion == "relative" or full_frame:
            frames = reenact_frames(reenactor, landmarks, rendered, latencies)
        else:  # the driver's landmarks as they are, composited as before retargeting existed
            rendered[:] = landmarks
            frames = render_frames(renderer, landmarks, background, 2.0 if args.feather is None else args.feather, latencies)
        for i, frame in enumerate(frames):
            if i in shown_left:
                left = fit_into(next(driver_iter) if driver_iter is not None else draw_landmarks(dots_on, landmarks[i]),
                                (h, w))
            video.write(np.concatenate([left, frame], 1) if args.side_by_side else frame)
            if i in sheet_idx:
                sheet_top.append(left)
                sheet_bottom.append(frame)
            progress.update(1)
        progress.close()
        video.finish()  # reopened and checked (a full disk shows here) before any other output is written
        if args.save_landmarks:
            with open(written.enter_context(atomic_path(args.save_landmarks)), "wb") as fh:
                np.save(fh, rendered, allow_pickle=False)
        if args.contact_sheet:
            write_image(written.enter_context(atomic_path(args.contact_sheet)), contact_sheet(sheet_top, sheet_bottom),
                        args.contact_sheet)
    wall = time.perf_counter() - t_start
    summary = latency_summary(latencies)
    summary.update({"out": str(out), "size": [out_w, h], "fps": fps, "wall_s": round(wall, 3),
                    "frames_per_s": round(n / wall, 1) if wall > 0 else None,
                    "skipped_no_face": int(n - summary["frames"]), "smooth": bool(args.smooth),
                    "regressor": metadata.get("regressor"), "threads": args.threads, "motion": args.motion,
                    "talking_head_graph": head is not None})
    if neutral is not None:
        summary["driver_neutral_row"] = neutral_row
    if args.save_landmarks:
        summary["landmarks_out"] = str(args.save_landmarks)
    if args.contact_sheet:
        summary["contact_sheet"] = str(args.contact_sheet)
    if latencies:
        m, f = summary["model_ms"], summary["frame_ms"]
        print(f"{n} frames -> {out} ({out_w}x{h}, {fps:g} fps) in {wall:.1f} s; latency ms p50/p90/p99: "
              f"model {m['p50']}/{m['p90']}/{m['p99']}, frame {f['p50']}/{f['p90']}/{f['p99']}")
    print(json.dumps(summary))
    return 0
