"""The page's face tracker (facesynth.web.track: the converted detector and attention mesh,
the Python reference of facesynth/web/page/tracker.js) against ``facesynth ingest --landmarker mediapipe``
(MediaPipe's own Face Mesh, refine_landmarks=True) on the same frames of shared clips.

Per clip: the median distance in pixels over all 478 points, over the irises (468-477), over
the refined lips and eyes, the 95th percentile, and the tracker's time per frame on one
thread (crop + mesh; the detector runs on the first frame only). Prints ONE JSON line.

    python -m bench.ingest.tracker [--clips lp_d3,lp_d6,vrt_face1] [--frames 100]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.harness import emit, load_average
from bench.ingest.ingest_mediapipe import _frames  # the clip's first frames, RGB

SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "faces"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", default="lp_d3,lp_d6,vrt_face1")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--root", default=str(SHARED), help="folder of clip folders with video.mp4")
    args = ap.parse_args()

    from facesynth.data.detect_mediapipe import MediaPipeLandmarker
    from facesynth.web import convert, mediapipe_ops
    from facesynth.web.track import OnnxFaceTracker

    table = mediapipe_ops.refinement_table()
    refined = np.flatnonzero(table >= 468)  # lips, eyes, irises: the points the refinement writes
    flags = set(Path("/proc/cpuinfo").read_text().split()) & {"avx2", "avx512f", "avx512_vnni", "avx_vnni"}
    out = {"bench": "tracker", "host_flags": sorted(flags), "load": load_average(), "clips": {}}
    with tempfile.TemporaryDirectory() as tmp:
        convert.convert_all(tmp)
        for clip in args.clips.split(","):
            video = Path(args.root) / clip / "video.mp4"
            if not video.is_file():
                print(f"error: {video}: no such video", file=sys.stderr)
                return 2
            frames = _frames(video, args.frames)
            tr, mp = OnnxFaceTracker(tmp), MediaPipeLandmarker()
            got, ms = [], []
            for rgb in frames:
                t0 = time.perf_counter()
                got.append(tr.track(rgb))
                ms.append((time.perf_counter() - t0) * 1e3)
            want = [mp.landmarks(rgb) for rgb in frames]
            mp.close()
            ok = [k for k, (g, w) in enumerate(zip(got, want, strict=True)) if g is not None and w is not None]
            err = np.linalg.norm(np.array([got[k] for k in ok]) - np.array([want[k] for k in ok]), axis=2)
            out["clips"][clip] = {
                "frames": len(frames), "both_found": len(ok),
                "median_px": round(float(np.median(err)), 3), "p95_px": round(float(np.percentile(err, 95)), 3),
                "iris_median_px": round(float(np.median(err[:, 468:])), 3),
                "refined_median_px": round(float(np.median(err[:, refined])), 3),
                "tracker_ms": round(float(np.median(ms[1:])), 2)}
    emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
