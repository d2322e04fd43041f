"""Benchmark of the ERI model: training time and per-frame synthesis time (steps 2-5:
SVR -> eigenERI -> R' x B_temp -> warp -> paste), printed as ONE JSON line.

With the ONNX part (default; ``--no-onnx`` skips it) the synthesizer is also exported
(``facesynth.onnx.eri``) and run with ONNX Runtime (``facesynth.runtime.EriRenderer``):
``onnx``: frames/s and ms per frame of the graph (FAPs -> crop/mask/placement) at batch 1
with 1 and 2 threads, batch-32 throughput, the same steps in torch eager at batch 1, the
file size and the largest |ONNX - torch| crop difference on the driving FAPs.

    python -m bench.train.eri                      # lp_d6, 300 training frames
    python -m bench.train.eri --train-frames 756 --synth-frames 64 --variant eps_rbf

Uses ../shared/data/faces/<clip> (training) and <target> (synthesis target); when the
data is absent it falls back to a small synthetic sequence and says so in the output.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from facesynth.data import load_sequence, shared_clip  # noqa: E402
from facesynth.eri.config import EriConfig  # noqa: E402
from facesynth.eri.geometry import select_neutral  # noqa: E402
from facesynth.eri.model import EriModel  # noqa: E402
from facesynth.eri.synthesis import EriSynthesizer  # noqa: E402


def _synthetic():
    from facesynth.data import FaceSequence
    from facesynth.data.frames import ArrayFrames
    from tests._faces import face_sequence_arrays

    frames, lm = face_sequence_arrays(40, 0)
    return FaceSequence.from_arrays(lm, ArrayFrames(frames), name="synthetic")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clip", default="lp_d6")
    p.add_argument("--target", default="lp_d10")
    p.add_argument("--train-frames", type=int, default=300, help="first N frames train (spread over the first 75%%)")
    p.add_argument("--synth-frames", type=int, default=64)
    p.add_argument("--variant", default=None, help="SVR variant used for synthesis (default: the model's)")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-onnx", action="store_true", help="skip the ONNX export / ONNX Runtime figures")
    p.add_argument("--reps", type=int, default=200, help="batch-1 frames timed per ONNX setting")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    path = shared_clip(a.clip)
    seq = load_sequence(path) if path else _synthetic()
    n75 = int(len(seq) * 0.75)
    rows = np.linspace(0, n75 - 1, min(a.train_frames, n75)).round().astype(int)
    cfg = EriConfig(batch_size=a.batch_size, compare=[])
    t0 = time.perf_counter()
    model = EriModel.fit(seq, rows, cfg)
    train_s = time.perf_counter() - t0

    tpath = shared_clip(a.target)
    tseq = load_sequence(tpath) if tpath else seq
    trow = select_neutral(tseq.landmarks)[0]
    drive = np.arange(n75, len(seq))[: a.synth_frames]
    faps = model.faps(seq.landmarks[drive])
    t1 = time.perf_counter()
    syn = EriSynthesizer(model, tseq.frame(trow), tseq.landmarks[trow], a.variant)
    setup_s = time.perf_counter() - t1
    syn.render(faps[:2], "eri")  # warm-up (warp module construction)
    t2 = time.perf_counter()
    n = sum(1 for _ in syn.iter_render(faps, "eri", a.batch_size))
    synth_s = (time.perf_counter() - t2) / n
    t3 = time.perf_counter()
    for s in range(0, len(faps), a.batch_size):
        syn.render(faps[s : s + a.batch_size], "geometry")
    geo_s = (time.perf_counter() - t3) / n
    onnx = None if a.no_onnx else bench_onnx(syn, faps, a.reps)
    print(json.dumps({
        "bench": "eri", "data": seq.name if path else "synthetic (shared data absent)", "target": tseq.name,
        "train_frames": int(len(rows)), "train_seconds": round(train_s, 3), "fit_seconds": model.meta["fit_seconds"],
        "n_components": model.pca.n_components, "mask_pixels": model.n_pixels, "variant": syn.variant,
        "support_vectors": int(len(model.regressors[syn.variant].sv)), "step1_seconds": round(setup_s, 4),
        "synth_frames": n, "synthesis_ms_per_frame": round(1000 * synth_s, 2),
        "geometry_only_ms_per_frame": round(1000 * geo_s, 2), "frame_size": list(tseq.image_size),
        "batch_size": a.batch_size, "threads": a.threads, "onnx": onnx,
    }))


def _per_frame(fn, n: int) -> float:
    """Median-of-3 seconds per call of fn() over n calls each."""
    times = []
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        times.append((time.perf_counter() - t) / n)
    return sorted(times)[1]


def bench_onnx(syn: EriSynthesizer, faps: np.ndarray, reps: int) -> dict:
    """ONNX Runtime vs torch eager figures of the exported ERI graph (see the module doc)."""
    import tempfile

    from facesynth.onnx.eri import export_eri, torch_reference
    from facesynth.runtime import EriRenderer

    with tempfile.TemporaryDirectory() as d:
        path = export_eri(syn, os.path.join(d, "eri.onnx"))
        size = os.path.getsize(path)
        out: dict = {"model_bytes": size}
        one = faps[:1]
        for threads in (1, 2):
            r = EriRenderer(path, threads=threads)
            r.render(one)
            s = _per_frame(lambda r=r: r.render(one), max(reps // 3, 1))
            out[f"batch1_threads{threads}_ms"] = round(1000 * s, 3)
            out[f"batch1_threads{threads}_fps"] = round(1 / s, 1)
        r = EriRenderer(path, threads=1)
        b32 = np.resize(faps, (32, faps.shape[1]))
        r.render(b32)
        s = _per_frame(lambda: r.render(b32), 2)
        out["batch32_threads1_fps"] = round(32 / s, 1)
        crop, mask, _ = r.render(faps, copy=True)
        t_crop, t_mask, _ = torch_reference(syn, faps)
        out["max_abs_diff_vs_torch"] = float(np.abs((crop - t_crop) * mask * t_mask).max())
        out["mask_pixels_differing"] = int((mask != t_mask).sum())
        out["n_scanline_events"] = int(r.metadata["n_scanline_events"])
        out["crop_size"] = list(r.crop_size)
    nt = torch.get_num_threads()
    torch.set_num_threads(1)
    torch_reference(syn, one)
    s = _per_frame(lambda: torch_reference(syn, one), max(reps // 10, 1))
    torch.set_num_threads(nt)
    out["torch_eager_batch1_threads1_ms"] = round(1000 * s, 3)
    out["torch_eager_batch1_threads1_fps"] = round(1 / s, 1)
    return out


if __name__ == "__main__":
    main()
