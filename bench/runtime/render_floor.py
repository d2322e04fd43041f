"""Batch-1 one-thread speed of exported runs against the floor of one render; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.runtime.render_floor RUN_DIR [RUN_DIR ...] [--rounds 5] [--frames 200]

For each run (a train.py run folder): exports it with ``facesynth export``'s defaults into a
temporary folder (ONNX size recorded), renders its held-out landmarks one frame at a time
with ONNX Runtime on one thread (``Renderer.render``), and times, in the same process, the
floor the issue sets: one appearance matmul (1 x 40 @ 40 x C M, float32 numpy) plus one
bilinear remap of a reference-size crop (``cv2.remap``, float32, 3 channels). Frames/s are the
best of ``--rounds`` rounds of ``--frames`` frames (wall clock: the figure least affected by
other jobs); ``ratio`` = floor frames/s over the model's.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from facesynth import progress  # noqa: E402
from facesynth.model.artifact import load_face_model  # noqa: E402
from facesynth.onnx.export import export_model  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.runtime.renderer import Renderer  # noqa: E402


def best_fps(step, rounds: int, frames: int) -> float:
    for _ in range(min(20, frames)):
        step(0)
    best = float("inf")
    for _ in range(rounds):
        t = time.perf_counter()
        for i in range(frames):
            step(i)
        best = min(best, (time.perf_counter() - t) / frames)
    return 1.0 / best


def floor_step(model):
    """One matmul + one remap at ``model``'s reference size, as a callable of the frame index."""
    h, w = model.reference.size
    rng = np.random.default_rng(0)
    basis = rng.standard_normal((40, model.n_channels * model.n_pixels)).astype(np.float32)
    b = np.ones((1, 40), np.float32)
    img = rng.random((h, w, 3)).astype(np.float32)
    mx, my = np.meshgrid(np.arange(w, dtype=np.float32) * 0.99 + 0.3, np.arange(h, dtype=np.float32) * 0.99 + 0.3)

    def step(_):
        b @ basis
        cv2.remap(img, mx, my, cv2.INTER_LINEAR)

    return step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    progress.set_quiet(True)
    cv2.setNumThreads(1)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for run in args.runs:
            seq, _, te = run_data(read_config(run))
            model = load_face_model(run / "face_model")
            path = Path(tmp) / f"{run.name}.onnx"
            export_model(run, path)
            rend = Renderer(path, threads=1)
            lm = seq.landmarks[te]
            fps = best_fps(lambda i, r=rend, x=lm: r.render(x[i % len(x)][None]), args.rounds, args.frames)
            floor = best_fps(floor_step(model), args.rounds, args.frames)
            out.append({"run": str(run), "data": seq.name, "frame": list(seq.frames.size),
                        "reference": list(model.reference.size), "reference_width": model.config.reference_width,
                        "onnx_mb": round(path.stat().st_size / 1e6, 2), "fps": round(fps, 1),
                        "floor_fps": round(floor, 1), "ratio": round(floor / fps, 2)})
    print(json.dumps({"runs": out}))


if __name__ == "__main__":
    main()
