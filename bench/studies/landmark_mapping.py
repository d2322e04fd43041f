"""Error of the 478 -> 68 mapping (facesynth/landmarks.py, ``mediapipe478.to_ibug68``)
against the shipped dlib landmarks of shared clips, per iBUG region.

For each clip, MediaPipe landmarks come from ``facesynth ingest --landmarker mediapipe``
(run here into a temporary folder, or read from ``--from-dir DIR/<clip>``), are mapped to
68 points, aligned per frame to the shipped dlib landmarks with a least-squares
similarity (Umeyama, all 68 points), and compared point by point. Prints ONE JSON line:
per clip and region the median and p95 distance in pixels and in % of the inter-ocular
distance (outer eye corners of the dlib landmarks), and the unaligned median.

    python -m bench.studies.landmark_mapping [--clips lp_d6 lp_d10 lp_d3] [--from-dir DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.harness import emit

REGIONS = ("jaw", "brows", "nose", "eyes", "outer_lips", "inner_lips")


def mapping_errors(lm478: np.ndarray, dlib68: np.ndarray) -> dict:
    """Per-region distances of mapped 478-point landmarks (T, 478, 2) to dlib's (T, 68, 2)."""
    from facesynth.geometry import apply_affine, similarity_fit
    from facesynth.landmarks import IBUG68, MEDIAPIPE478, inter_ocular

    ok = np.isfinite(lm478).all(axis=(1, 2)) & np.isfinite(dlib68).all(axis=(1, 2))
    mapped = MEDIAPIPE478.to_ibug68(lm478[ok]).astype(np.float64)
    ref = dlib68[ok].astype(np.float64)
    aligned = apply_affine(mapped, similarity_fit(mapped, ref))
    d = np.linalg.norm(aligned - ref, axis=-1)  # (T, 68)
    d_raw = np.linalg.norm(mapped - ref, axis=-1)
    iod = inter_ocular(ref)[:, None]
    out = {"frames": int(ok.sum()), "frames_missing": int((~ok).sum()), "iod_px_median": round(float(np.median(iod)), 2)}
    for name in ("all",) + REGIONS:
        idx = np.arange(68) if name == "all" else IBUG68.region(name)
        out[name] = {
            "median_px": round(float(np.median(d[:, idx])), 3),
            "p95_px": round(float(np.percentile(d[:, idx], 95)), 3),
            "median_pct_iod": round(float(np.median(d[:, idx] / iod)) * 100, 3),
            "mean_px": round(float(d[:, idx].mean()), 3),
            "unaligned_median_px": round(float(np.median(d_raw[:, idx])), 3),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", nargs="+", default=["lp_d6", "lp_d10", "lp_d3"])
    ap.add_argument("--from-dir", type=Path, help="read DIR/<clip>/landmarks.npy (mediapipe478 ingest folders) instead of ingesting")
    args = ap.parse_args()

    from facesynth.data import load_landmarks
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_clip

    out = {"bench": "landmark_mapping", "alignment": "per-frame similarity (Umeyama) of the mapped 68 points onto dlib's"}
    with tempfile.TemporaryDirectory(prefix="landmark_mapping_") as tmp:
        for clip in args.clips:
            src = shared_clip(clip)
            if src is None:
                out[clip] = "absent"
                continue
            if args.from_dir:
                lm = load_landmarks(args.from_dir / clip, scheme="mediapipe478")
            else:
                ingest_video(src / "video.mp4", Path(tmp) / clip, landmarker="mediapipe")
                lm = load_landmarks(Path(tmp) / clip)
            dlib = load_landmarks(src)
            n = min(len(lm), len(dlib))
            out[clip] = mapping_errors(lm[:n], dlib[:n])
    emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
