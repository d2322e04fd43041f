"""``facesynth app``: render a talking-head video from landmarks with an exported model.

    facesynth app --model model.onnx (--landmarks L.npy | --video DRIVER.mp4) --out out.mp4
                  [--motion relative|absolute] [--driver-neutral N] [--save-landmarks L.npy]
                  [--background IMG] [--side-by-side] [--smooth] [--size WxH]

A thin command line round :class:`facesynth.runtime.pipeline.AvatarPipeline`, which does the
per-frame work: a talking-head file (``facesynth export RUN --talking-head``) renders each
frame in one ONNX Runtime call; a face model is driven through the numpy pipeline (each
frame's landmarks retargeted onto the avatar, ``--motion relative``, the default; the avatar's
own frame warped with the face and the face composited with a feathered, colour-matched
seam), batch 1, as a live app would. This module reads the driver (landmarks or a video,
frame by frame), picks the background, and writes the video atomically (mp4v) at the
driver's own frame rate; a progress bar shows frames/s, the summary gives latency
percentiles of the model call and of the whole frame. Torch is never imported.

Every output path is checked, and refused when it is one of the inputs, before the model is
loaded; the video is reopened and checked before it is kept
(:func:`facesynth.videofile.atomic_video`), and all outputs are renamed into place together.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import logging
import os
import time
from pathlib import Path

import cv2
import numpy as np

from facesynth.compositing import GREY
from facesynth.data.sequence import check_landmarks_in_frame
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path, check_writable, refuse_overwriting_inputs
from facesynth.progress import bar, result, stage
from facesynth.runtime.checks import check_coordinate_range, check_face_extent, check_frame_size
from facesynth.runtime.video import (
    contact_sheet,
    detect_video_landmarks,
    draw_landmarks,
    fit_into,
    write_image,
)
from facesynth.videofile import atomic_video

log = logging.getLogger(__name__)
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
    """FacesynthError naming ``where`` when the driver has no frame, no frame with a face, or a
    face whose points all lie within 1 px."""
    if not len(landmarks):
        raise FacesynthError(f"{where}: holds no frames (0 landmark rows), nothing to render")
    if not np.isfinite(landmarks).all(axis=(1, 2)).any():
        rows = f"the first {len(landmarks)} rows (--max-frames)" if max_frames else f"all {len(landmarks)} rows"
        raise FacesynthError(f"{where}: no frame has a face ({rows} are NaN), nothing to render")
    check_face_extent(landmarks, str(where))  # a face collapsed to a point cannot be aligned (NaN rows pass)


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
    wanted = min(len(driver), max_frames or len(driver))
    if len(landmarks) < wanted:  # a file cut short (a faststart mp4 keeps its whole index): say so, render what decodes
        log.warning("%s: only %d of the %d frames its header declares decode (a truncated file?); rendering %d frames",
                    driver.path, len(landmarks), len(driver), len(landmarks))
    return landmarks


def check_head_options(args: argparse.Namespace, model: str) -> None:
    """FacesynthError naming the options a talking-head file fixes at export (its own frame,
    relative motion, its seam)."""
    fixed = [opt for opt, given in (("--background", args.background), ("--motion absolute", args.motion == "absolute"),
                                    ("--feather", args.feather is not None), ("--no-colour-match", args.no_colour_match),
                                    ("--size", args.size)) if given]
    if fixed:
        raise FacesynthError(f"{model} is a talking-head file (its frame, relative motion and seam are fixed at "
                             f"export): {', '.join(fixed)} cannot apply; export the face model for that "
                             "(facesynth export RUN --out M.onnx)")


# ------------------------------------------------------------------ command
def driver_sources(args: argparse.Namespace, outputs: list[str]) -> tuple[str | None, float | None]:
    """The driver's video (to show or to read its rate; None when not needed) and the frame
    rate an ingest folder's meta.json records; refuses outputs that are inputs."""
    from facesynth.data.readers import ingest_video

    meta_fps = driver_video = None
    inputs = [args.model, args.background, args.video, args.landmarks, args.driver_video]
    if args.landmarks and Path(args.landmarks).is_dir():  # an ingest folder: its meta.json names the video and rate
        folder_video, meta_fps = ingest_video(args.landmarks)
        inputs += [Path(args.landmarks, "landmarks.npy"), Path(args.landmarks, "meta.json"), folder_video]
        # its video is opened when its frames are shown, or for its frame rate when meta.json has none
        driver_video = folder_video if args.side_by_side or args.contact_sheet or meta_fps is None else None
    refuse_overwriting_inputs(outputs, inputs)
    return args.video or args.driver_video or driver_video, meta_fps


def open_pipeline(args: argparse.Namespace):
    """The :class:`AvatarPipeline` of ``--model`` and the options; ``args.motion`` set to its motion."""
    from facesynth.retarget import RETARGET_SCHEMES
    from facesynth.runtime.pipeline import AvatarPipeline

    pipeline = AvatarPipeline(args.model, args.motion, still=bool(args.background), feather=args.feather,
                              match_colour=not args.no_colour_match, threads=args.threads)
    if pipeline.head:
        check_head_options(args, args.model)
    elif args.motion is None and pipeline.motion == "absolute":
        log.warning("%s has no avatar metadata (%s): --motion absolute", args.model, "an older export"
                    if pipeline.scheme in RETARGET_SCHEMES else f"retargeting does not take {pipeline.scheme} landmarks")
    missing = pipeline.avatar.missing(pipeline.motion, pipeline.full_frame)
    if missing:
        log.warning("%s was exported by an older version, without %s: re-export it with this version", args.model,
                    ", ".join(missing))
    args.motion = pipeline.motion
    return pipeline


def read_driver(args: argparse.Namespace, driver, driver_video, scheme: str) -> np.ndarray:
    """(T, P, 2) driver landmarks in ``scheme``: detected in ``--video``, or read from
    ``--landmarks`` (mediapipe478 ones mapped for an ibug68 model), checked before any work."""
    from facesynth.data.readers import load_landmarks

    if args.video:
        return detect_with_progress(driver, args.max_frames, scheme, not args.quiet)
    landmarks = load_landmarks(args.landmarks, scheme=scheme)  # mediapipe478 -> ibug68 is mapped; the reverse is an error
    if args.max_frames:
        landmarks = landmarks[: args.max_frames]
    check_faces(landmarks, args.landmarks, args.max_frames)
    if (args.side_by_side or args.contact_sheet) and driver is not None and 0 < len(driver) < len(landmarks):
        # the header's count, before any work; reading the frames checks the rest
        raise FacesynthError(f"{driver_video}: {len(driver)} frames for {len(landmarks)} landmark rows")
    return landmarks


def choose_background(args: argparse.Namespace, pipeline, driver, landmarks: np.ndarray) -> np.ndarray:
    """uint8 (H, W, 3): ``--background``, the avatar's own frame (warped with the face), or grey
    of the driver video's size, ``--size`` or the landmarks' extent."""
    if args.background:
        return load_background(args.background, (0, 0))
    if pipeline.full_frame:  # the avatar's own frame, warped so that its whole head follows the face
        return pipeline.avatar.background
    if driver is not None and not args.size:
        h, w = driver.size
        return load_background(None, (w, h))
    return load_background(None, parse_size(args.size) if args.size else default_size(landmarks))


def write_outputs(args: argparse.Namespace, pipeline, landmarks: np.ndarray, neutral, background: np.ndarray,
                  driver, fps: float) -> tuple[list, np.ndarray]:
    """Render every frame into ``--out`` (driver beside it with ``--side-by-side``), then the
    landmarks and the contact sheet; all renamed into place together. Returns the latencies
    and the avatar landmarks rendered (T, P, 2)."""
    h, w = background.shape[:2]
    # without a driver video, its dots are drawn in its own frame (not on the avatar's face)
    dots_on = background if args.motion == "absolute" or driver is not None else \
        load_background(None, default_size(landmarks))
    n = len(landmarks)
    latencies: list = []
    rendered = np.full((n, pipeline.n_points, 2), np.nan, np.float32)  # the avatar landmarks of each frame (--save-landmarks)
    sheet_idx = set(np.linspace(0, n - 1, min(6, n)).round().astype(int).tolist()) if args.contact_sheet else set()
    sheet_top, sheet_bottom = [], []
    shown_left = set(range(n)) if args.side_by_side else sheet_idx  # the frames that need the driver's picture
    driver_iter = driver.read(sorted(shown_left)) if driver is not None else None
    with contextlib.ExitStack() as written:  # every output is renamed into place only once all are written
        video = written.enter_context(atomic_video(Path(args.out), fps, (2 * w if args.side_by_side else w, h)))
        progress = bar(total=n, unit="frame", desc="app", enabled=not args.quiet)
        pipeline.start(neutral, background)
        for i, frame in enumerate(pipeline.frames(landmarks, rendered, latencies)):
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
    return latencies, rendered


def run(args: argparse.Namespace) -> int:
    from facesynth.data.frames import VideoFrames
    from facesynth.runtime.filters import smooth_landmarks
    from facesynth.runtime.pipeline import latency_summary
    from facesynth.runtime.reenact import driver_neutral_of

    outputs = check_options(args)  # before any decoding or rendering
    driver_video, meta_fps = driver_sources(args, outputs)
    pipeline = open_pipeline(args)
    driver = VideoFrames(driver_video) if driver_video else None  # decoded frame by frame, never held whole
    video_fps = driver.fps if driver is not None and 0 < driver.fps < 1e4 else None
    landmarks = read_driver(args, driver, driver_video, pipeline.scheme)
    fps = float(args.fps or meta_fps or video_fps or 30.0)
    if not (args.fps or meta_fps or video_fps):
        log.info("%s records no frame rate: %g fps (--fps sets it)", args.video or args.landmarks, fps)
    if args.smooth:
        landmarks = smooth_landmarks(landmarks, fps, args.min_cutoff, args.beta)
    neutral = neutral_row = None
    if args.motion == "relative" or args.driver_neutral is not None:
        neutral, neutral_row = driver_neutral_of(landmarks, args.driver_neutral)
    background = choose_background(args, pipeline, driver, landmarks)
    h, w = background.shape[:2]
    # before any rendering; the driver's points are in its own frame, when known
    check_landmarks_in_frame(landmarks, (w, h) if driver is None else driver.size[::-1], args.landmarks or args.video,
                             margin=1.0)
    t_start = time.perf_counter()
    latencies, _ = write_outputs(args, pipeline, landmarks, neutral, background, driver, fps)
    wall, n, out_w = time.perf_counter() - t_start, len(landmarks), 2 * w if args.side_by_side else w
    summary = latency_summary(latencies)
    summary.update({"out": str(args.out), "size": [out_w, h], "fps": fps, "wall_s": round(wall, 3),
                    "frames_per_s": round(n / wall, 1) if wall > 0 else None,
                    "skipped_no_face": int(n - summary["frames"]), "smooth": bool(args.smooth),
                    "regressor": pipeline.metadata.get("regressor"), "threads": args.threads, "motion": args.motion,
                    "talking_head_graph": pipeline.head is not None})
    extra = {"driver_neutral_row": neutral_row, "landmarks_out": args.save_landmarks, "contact_sheet": args.contact_sheet}
    summary.update({k: v for k, v in extra.items() if v is not None})
    line = f"{n} frames -> {args.out} ({out_w}x{h}, {fps:g} fps) in {wall:.1f} s"
    if latencies:
        m, f = summary["model_ms"], summary["frame_ms"]
        line += (f"; latency ms p50/p90/p99: model {m['p50']}/{m['p90']}/{m['p99']}, "
                 f"frame {f['p50']}/{f['p90']}/{f['p99']}")
    result(line, summary)
    return 0
