"""Speed and parity of the talking-head ONNX graph (facesynth.onnx.talking_head) against the
face-only synthesis graph and the numpy reference pipeline, in one run; one JSON line.

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/bench_talking_head_graph.py [--avatar lp_d10] [--driver lp_d13]
        [--frames 60] [--work /tmp/facesynth_th_graph]

The avatar: a linear model of the first 75 % of ``--avatar`` (every 3rd frame), exported as
the synthesis file (with its avatar metadata) and as the talking-head file. Timing: ONNX
Runtime, one intra-op thread, batch 1, the two graphs interleaved frame by frame over
``--frames`` driver frames (median ms). Parity: every frame against
:class:`facesynth.runtime.Reenactor` (full-frame warp, relative motion, the graph's feather):
the largest pixel difference (0-255), the frames' pixels above 2, the largest retargeted
landmark difference (px).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--avatar", default="lp_d10")
    ap.add_argument("--driver", default="lp_d13")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--work", default="/tmp/facesynth_th_graph")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    face, head = build(args.avatar, work)

    from facesynth.runtime import Reenactor, Renderer
    from facesynth.runtime.reenact import driver_neutral_of
    from facesynth.runtime.talking_head import TalkingHead

    lm = np.load(Path("../shared/data/faces") / args.driver / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    rows = [i for i in np.linspace(0, len(lm) - 1, args.frames).astype(int) if np.isfinite(lm[i]).all()]
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
    print(json.dumps({
        "avatar": args.avatar, "driver": args.driver, "frames": len(rows), "frame_size": [w, h], "threads": 1,
        "talking_head_ms": round(head_ms, 2), "talking_head_fps": round(1e3 / head_ms, 1),
        "face_only_ms": round(face_ms, 3), "face_only_fps": round(1e3 / face_ms, 1),
        "ratio_head_to_face": round(head_ms / face_ms, 1), "feather_px": th.feather,
        "max_pixel_diff": worst, "max_pixels_above_2": max(beyond), "mean_pixels_above_2": round(float(np.mean(beyond)), 1),
        "max_landmark_diff_px": round(worst_lm, 5), "head_onnx_mb": round(head.stat().st_size / 1e6, 1),
    }))


if __name__ == "__main__":
    main()
