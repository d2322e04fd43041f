"""The talking head's outline under head motion: the full-frame warp's node grid against the
exact piecewise affine warp, along the head's outline; one JSON line per clip.

    python -m bench.studies.outline [--clips lp_d3,lp_d10] [--steps 8,4] [--frames 12]

Per clip: the avatar's warp as an export builds it (the neutral among the first 75 % of the
frames, :func:`facesynth.neutral.select_neutral`; its motion learned from those frames and
its ring chosen on them, :func:`facesynth.onnx.avatar.frame_motion`), driven by ``--frames``
evenly spaced held-out frames' own landmarks (no retargeting, the head's motion as filmed),
at each node spacing of ``--steps`` (px). Figures (:func:`facesynth.eval.jaggedness.outline_figures`,
over the silhouette band: jaw, hair, neck): ``map_px_p99`` / ``map_px_max``, how far the map
departs from the exact one (px), and ``staircase``, the gradient energy that departure draws
over the edges' own; medians over the frames and the worst frame's. No model is trained.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from facesynth.data import load_sequence, shared_clip, temporal_split
from facesynth.eval.jaggedness import exact_warp, outline_figures
from facesynth.neutral import select_neutral
from facesynth.onnx.avatar import frame_motion
from facesynth.runtime.fullframe import FrameWarp


def clip_figures(clip: str, steps: list[int], frames: int) -> dict:
    seq = load_sequence(shared_clip(clip))
    train, test = temporal_split(len(seq))
    lm = np.asarray(seq.landmarks[train], np.float32)
    idx = select_neutral(lm)[0]
    frame = np.asarray(seq.frame(int(train[idx])))
    motion = frame_motion(frame, lm[idx], lm, train, seq)
    warps = {k: FrameWarp(frame, lm[idx], motion=np.asarray(motion["coefficients"]), ring_scale=motion["ring_scale"],
                          grid_step=k) for k in steps}
    exact = exact_warp(warps[steps[0]])
    rows = test[np.unique(np.linspace(0, len(test) - 1, min(frames, len(test))).round().astype(int))]
    out = {"bench": "outline", "clip": clip, "frame_size": list(seq.image_size), "frames": len(rows),
           "neutral_row": int(train[idx]), "ring_scale": motion["ring_scale"]}
    for k, fw in warps.items():
        got = [outline_figures(fw, seq.landmarks[r], exact) for r in rows]
        out[f"step{k}"] = {**{key: round(float(np.median([g[key] for g in got])), 4) for key in got[0]},
                           **{f"worst_{key}": round(float(max(g[key] for g in got)), 4) for key in got[0]}}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", default="lp_d3,lp_d10,lp_d13", help="shared clips, comma-separated")
    ap.add_argument("--steps", default="8,4", help="node spacings (px) to compare, comma-separated")
    ap.add_argument("--frames", type=int, default=12, help="held-out frames per clip, evenly spaced")
    a = ap.parse_args()
    steps = [int(s) for s in a.steps.split(",")]
    for clip in a.clips.split(","):
        t0 = time.perf_counter()
        line = clip_figures(clip, steps, a.frames)
        line["seconds"] = round(time.perf_counter() - t0, 1)
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
