"""Speed and parity of the talking-head ONNX graph (facesynth.onnx.talking_head) against the
face-only synthesis graph and the numpy reference pipeline, in one run; one JSON line.

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/bench_talking_head_graph.py [--pairs lp_d3<-lp_d6,...]
        [--frames 0] [--work /tmp/facesynth_th_graph]

Per pair AVATAR<-DRIVER: a linear model of the first 75 % of the avatar's clip (every 3rd
frame), exported as the synthesis file (with its avatar metadata) and as the talking-head
file. Timing: ONNX Runtime, one intra-op thread, batch 1, the two graphs interleaved frame by
frame (median ms). Parity: each driver frame (``--frames 0``: every one; else that many,
evenly spread) against :class:`facesynth.runtime.Reenactor` (full-frame warp, relative
motion, the graph's feather): the largest pixel difference (0-255), the frames' pixels above
2, the largest retargeted landmark difference (px). ``max_pixel_diff`` over all pairs at the
top level.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facesynth.runtime.cpu import cpu_flags  # noqa: E402


def build(avatar: str, work: Path) -> tuple[Path, Path]:
    from facesynth.data import load_sequence, temporal_split
    from facesynth.model import FaceModel
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.onnx.talking_head import export_talking_head
    from facesynth.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    seq = load_sequence(Path("../shared/data/faces") / avatar)
    train, _ = temporal_split(len(seq))
    rows = train[::3]
    model = FaceModel.fit(seq, rows=rows, progress=False)
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows), clamp=True)
    syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
    meta = avatar_metadata(syn, seq.landmarks[train], train, seq)
    face, head = work / f"{avatar}_face.onnx", work / f"{avatar}_head.onnx"
    export_synthesizer(syn, face, meta)
    export_talking_head(syn, meta, head)
    return face, head


def run_pair(avatar: str, driver: str, frames: int, work: Path) -> dict:
    from facesynth.runtime import Reenactor, Renderer
    from facesynth.runtime.reenact import driver_neutral_of
    from facesynth.runtime.talking_head import TalkingHead

    face, head = build(avatar, work)
    lm = np.load(Path("../shared/data/faces") / driver / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    picked = range(len(lm)) if frames <= 0 else np.linspace(0, len(lm) - 1, frames).astype(int)
    rows = [i for i in picked if np.isfinite(lm[i]).all()]
    th = TalkingHead(head, driver_neutral=neutral, threads=1)
    renderer = Renderer(face, threads=1)
    ref = Reenactor(face, driver_neutral=neutral, feather=th.feather, full_frame=True)
    t_head, t_face, worst, beyond, worst_lm = [], [], 0, [], 0.0
    for i in rows:
        want, want_lm = ref.step(lm[i])
        t0 = time.perf_counter()
        got, got_lm = th.run(lm[i][None])
        t1 = time.perf_counter()
        renderer.render(want_lm[None])
        t2 = time.perf_counter()
        t_head.append(t1 - t0)
        t_face.append(t2 - t1)
        diff = np.abs(got[0].astype(int) - want).max(-1)
        worst, worst_lm = max(worst, int(diff.max())), max(worst_lm, float(np.abs(got_lm[0] - want_lm).max()))
        beyond.append(int((diff > 2).sum()))
    head_ms, face_ms = 1e3 * float(np.median(t_head)), 1e3 * float(np.median(t_face))
    w, h = th.frame_size
    return {
        "avatar": avatar, "driver": driver, "frames": len(rows), "frame_size": [w, h], "threads": 1,
        "talking_head_ms": round(head_ms, 2), "talking_head_fps": round(1e3 / head_ms, 1),
        "face_only_ms": round(face_ms, 3), "face_only_fps": round(1e3 / face_ms, 1),
        "ratio_head_to_face": round(head_ms / face_ms, 1), "feather_px": th.feather,
        "max_pixel_diff": worst, "max_pixels_above_2": max(beyond), "mean_pixels_above_2": round(float(np.mean(beyond)), 1),
        "max_landmark_diff_px": round(worst_lm, 5), "head_onnx_mb": round(head.stat().st_size / 1e6, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", default="lp_d3<-lp_d6", help="AVATAR<-DRIVER,... (a clip driving itself: lp_d3<-lp_d3)")
    ap.add_argument("--frames", type=int, default=60, help="driver frames per pair, evenly spread (0: every frame)")
    ap.add_argument("--work", default="/tmp/facesynth_th_graph")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    pairs = [run_pair(*p.split("<-"), args.frames, work) for p in args.pairs.split(",")]
    print(json.dumps({"cpu_flags": sorted(cpu_flags(Path("/proc/cpuinfo").read_text()) & {"avx2", "avx512_vnni", "avx_vnni"}),
                      "load_avg": round(os.getloadavg()[0], 2), "max_pixel_diff": max(p["max_pixel_diff"] for p in pairs),
                      "max_landmark_diff_px": max(p["max_landmark_diff_px"] for p in pairs), "pairs": pairs}))


if __name__ == "__main__":
    main()
