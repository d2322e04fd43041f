"""Ingest throughput: frames/s of `facesynth ingest` (decode + dlib HOG detection + 68-point fit).

Prints ONE JSON line. By default ingests ../shared/data/faces/lp_d6/video.mp4 (all 1008
frames) and also reports the landmark error against the shipped landmarks.npy; without
the shared data it ingests a synthetic video (the embedded subject, written to a temp
file) and reports the error against its known landmarks.

    python -m bench.ingest.ingest [--video PATH] [--max-frames N] [--every N] [--synthetic]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from bench.harness import emit, load_average


def _synthetic_video(folder: Path, n: int) -> tuple[Path, np.ndarray]:
    from facesynth.data.synthetic import make_synthetic_sequence

    seq = make_synthetic_sequence(n_frames=n, size=256, seed=0)
    path = folder / "synthetic.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), seq.fps, (256, 256))
    for f in seq.iter_frames():
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    return path, seq.landmarks


def main() -> int:
    tmp = Path(tempfile.mkdtemp(prefix="bench_ingest_"))
    try:
        return _run(tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run(tmp: Path) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--video", help="video to ingest (default: shared lp_d6, else a synthetic clip)")
    ap.add_argument("--clip", default="lp_d6", help="shared clip name when --video is not given")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--synthetic", action="store_true", help="ingest a synthetic clip even when shared data exists")
    args = ap.parse_args()

    from facesynth.data.detect import LandmarkDetector
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_clip

    reference = None
    if args.video:
        video, source = Path(args.video), "file"
        if (video.parent / "landmarks.npy").is_file():
            reference = np.load(video.parent / "landmarks.npy")
    elif not args.synthetic and (clip := shared_clip(args.clip)) is not None:
        video, source, reference = clip / "video.mp4", f"shared:{args.clip}", np.load(clip / "landmarks.npy")
    else:
        video, reference = _synthetic_video(tmp, args.max_frames or 150)
        source = "synthetic"

    t0 = time.perf_counter()
    detector = LandmarkDetector()
    load_s = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    ingest_video(video, tmp / "out", every=args.every, max_frames=args.max_frames, detector=detector)
    total_s = time.perf_counter() - t0
    cpu_s = time.process_time() - c0
    meta = json.loads((tmp / "out" / "meta.json").read_text())
    st = meta["stats"]
    lm = np.load(tmp / "out" / "landmarks.npy")
    out = {
        "bench": "ingest",
        "video": str(video),
        "source": source,
        "resolution": [meta["video"]["width"], meta["video"]["height"]],
        "frames_processed": st["frames_processed"],
        "detector_load_s": round(load_s, 3),
        "ingest_s": round(total_s, 3),
        "frames_per_s": round(st["frames_processed"] / total_s, 2),
        "ingest_cpu_s": round(cpu_s, 3),
        "frames_per_cpu_s": round(st["frames_processed"] / cpu_s, 2),
        "load_avg_1min": round(load_average(), 2),
        "ms_per_frame": {k: round(v, 2) for k, v in st["timing_ms_per_frame"].items()},
        "detection_rate": st["detection_rate"],
        "det_source_counts": st["det_source_counts"],
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "dlib": meta["detector_versions"].get("dlib"),
    }
    if reference is not None:
        n = min(len(lm), len(reference))
        ok = np.isfinite(lm[:n, 0, 0]) & np.isfinite(reference[:n, 0, 0])
        err = np.linalg.norm(lm[:n][ok] - reference[:n][ok], axis=-1)
        out["median_err_px_vs_reference"] = round(float(np.median(err)), 4)
        out["max_err_px_vs_reference"] = round(float(err.max()), 4)
    emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
