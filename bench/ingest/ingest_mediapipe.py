"""MediaPipe ingest throughput on one core: frames/s of Face Mesh (478 points, video mode)
at the clip's own size and at 480x480, and of the whole `facesynth ingest --landmarker
mediapipe` (decode + landmarks + writing).

The process is pinned to one CPU (``os.sched_setaffinity``), so every thread MediaPipe
starts shares that core. Frames are decoded into memory first, so the landmark figures
exclude decoding. ``frames_per_cpu_s`` (process CPU time) is less sensitive to other
processes on a shared machine than the wall-clock ``frames_per_s``; both are printed,
with the load average. Prints ONE JSON line.

    python -m bench.ingest.ingest_mediapipe [--clip lp_d6 | --video PATH] [--frames 300]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from bench.harness import emit, load_average


def _frames(path: Path, n: int) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    out = []
    while len(out) < n:
        ok, bgr = cap.read()
        if not ok:
            break
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    cap.release()
    return out


def _landmark_rate(frames: list[np.ndarray]) -> dict:
    from facesynth.data.detect_mediapipe import MediaPipeLandmarker

    mp = MediaPipeLandmarker()
    mp.landmarks(frames[0])  # first call: graph start-up and the initial detection
    mp.reset()
    t0, c0 = time.perf_counter(), time.process_time()
    found = sum(mp.landmarks(f) is not None for f in frames)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    mp.close()
    return {
        "size_wh": [int(frames[0].shape[1]), int(frames[0].shape[0])],
        "frames": len(frames),
        "found": int(found),
        "frames_per_s": round(len(frames) / wall, 1),
        "frames_per_cpu_s": round(len(frames) / cpu, 1),
        "ms_per_frame": round(1000 * wall / len(frames), 3),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="lp_d6", help="shared clip (default lp_d6)")
    ap.add_argument("--video", type=Path, help="a video file instead of a shared clip")
    ap.add_argument("--frames", type=int, default=300, help="frames to time (default 300)")
    ap.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the first allowed)")
    args = ap.parse_args()

    from facesynth.data.detect_mediapipe import check_extra, mediapipe_versions
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_clip

    check_extra()
    cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    if args.video:
        video = args.video
    else:
        clip = shared_clip(args.clip)
        if clip is None:
            print(json.dumps({"bench": "ingest_mediapipe", "skipped": f"shared clip {args.clip} absent"}))
            return 0
        video = clip / "video.mp4"
    frames = _frames(video, args.frames)
    small = [cv2.resize(f, (480, 480), interpolation=cv2.INTER_AREA) for f in frames]
    out = {
        "bench": "ingest_mediapipe",
        "video": str(video),
        "cpu_pinned": cpu,
        "load_avg_1min": round(load_average(), 2),
        "clip_size": _landmark_rate(frames),
        "at_480x480": _landmark_rate(small),
    }
    with tempfile.TemporaryDirectory(prefix="bench_mp_") as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        seq = ingest_video(video, Path(tmp) / "out", landmarker="mediapipe", max_frames=args.frames)
        wall, cpu_s = time.perf_counter() - t0, time.process_time() - c0
        st = seq.meta["stats"]
        out["ingest"] = {
            "frames": st["frames_processed"], "detection_rate": st["detection_rate"],
            "frames_per_s": round(st["frames_processed"] / wall, 1), "frames_per_cpu_s": round(st["frames_processed"] / cpu_s, 1),
            "ms_per_frame": {k: round(v, 3) for k, v in st["timing_ms_per_frame"].items()},
        }
    out["load_avg_1min_end"] = round(load_average(), 2)
    out["versions"] = mediapipe_versions()
    emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
