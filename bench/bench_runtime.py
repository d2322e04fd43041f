"""Runtime benchmark: exported synthesis models in ONNX Runtime vs torch eager.

Fits a face model on a real clip (default lp_d6, every 2nd frame), fits every registered
SADM regressor on it, exports each to ONNX and measures, at the model's reference size:

* per-frame latency at batch 1 with 1 and 2 threads (median and p90 wall clock, and the
  median CPU time of the calling process, which is less affected by other load);
* throughput at batch 32 (frames/s, 1 thread);
* the same for torch eager (``Synthesizer.forward``, ``torch.set_num_threads``);
* model file size, support vectors (SVR), appearance components, peak RSS.

Prints ONE JSON line.

    PYTHONPATH=. python bench/bench_runtime.py [--regressors linear,mlp] [--n-appearance 50] [--reps 300]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _times(fn, reps: int, warmup: int = 5) -> dict:
    for _ in range(warmup):
        fn(0)
    wall, cpu = [], []
    for i in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn(i)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    w, c = np.asarray(wall) * 1e3, np.asarray(cpu) * 1e3
    return {"wall_ms_p50": round(float(np.median(w)), 4), "wall_ms_p90": round(float(np.percentile(w, 90)), 4),
            "cpu_ms_p50": round(float(np.median(c)), 4)}


def _throughput(fn, reps: int, batch: int) -> dict:
    t = _times(fn, reps, warmup=2)
    return {"batch": batch, "frames_per_s_wall": round(batch / t["wall_ms_p50"] * 1e3, 1),
            "frames_per_s_cpu": round(batch / t["cpu_ms_p50"] * 1e3, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", default="lp_d6")
    p.add_argument("--step", type=int, default=2, help="training rows: every STEP-th frame")
    p.add_argument("--n-appearance", type=int, default=None, help="appearance components (default: 98%% variance)")
    p.add_argument("--regressors", default="", help="comma-separated names (default: every registered one)")
    p.add_argument("--reps", type=int, default=300, help="batch-1 repetitions per setting")
    p.add_argument("--reps32", type=int, default=20, help="batch-32 repetitions")
    args = p.parse_args(argv)

    import torch

    from facesynth.data import load_sequence, shared_clip
    from facesynth.export_onnx import export_synthesizer
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.runtime import Renderer
    from facesynth.sadm.regressors import REGISTRY
    from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer

    clip = shared_clip(args.clip)
    if clip is None:
        print(json.dumps({"error": f"shared clip {args.clip!r} is absent"}))
        return 2
    seq = load_sequence(clip)
    rows = np.arange(0, len(seq), args.step)
    t0 = time.perf_counter()
    model = FaceModel.fit(seq, FaceModelConfig(n_appearance=args.n_appearance), rows=rows, progress=False)
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows))
    fit_s = time.perf_counter() - t0
    lm = seq.landmarks.astype(np.float32)
    n = len(lm)
    names = [s for s in args.regressors.split(",") if s] or sorted(REGISTRY)
    out = {
        "bench": "runtime", "clip": args.clip, "train_frames": int(len(rows)),
        "reference_size": list(model.reference.size), "n_shape": model.shape_pca.n_components,
        "n_appearance": model.appearance_pca.n_components, "n_triangles": model.reference.n_triangles,
        "cpu_count": os.cpu_count(), "loadavg_at_start": [round(v, 2) for v in os.getloadavg()],
        "model_fit_s": round(fit_s, 1), "regressors": {},
    }
    tmp = Path(tempfile.mkdtemp(prefix="bench_runtime_"))
    for name in names:
        entry: dict = {}
        t0 = time.perf_counter()
        reg = REGISTRY[name].fit(x, y, seed=0)
        entry["fit_s"] = round(time.perf_counter() - t0, 2)
        entry["summary"] = reg.summary()
        syn = Synthesizer(model, GlobalAppearance(model, reg)).eval()
        path = export_synthesizer(syn, tmp / f"{name}.onnx", {"data_fingerprint": model.fingerprint})
        entry["onnx_bytes"] = path.stat().st_size
        ort_res = {}
        for threads in (1, 2):
            r = Renderer(path, threads=threads)
            ort_res[f"batch1_threads{threads}"] = _times(lambda i: r.render(lm[i % n: i % n + 1]), args.reps)
        r = Renderer(path, threads=1)
        starts = np.arange(0, n - 32, 32)
        ort_res["batch32_threads1"] = _throughput(lambda i: r.render(lm[starts[i % len(starts)]:][:32]), args.reps32, 32)
        b1 = ort_res["batch1_threads1"]
        ort_res["frames_per_s_batch1_threads1"] = {"wall": round(1e3 / b1["wall_ms_p50"], 1), "cpu": round(1e3 / b1["cpu_ms_p50"], 1)}
        entry["onnxruntime"] = ort_res
        torch_res = {}
        xt = torch.from_numpy(lm)
        with torch.no_grad():
            for threads in (1, 2):
                torch.set_num_threads(threads)
                torch_res[f"batch1_threads{threads}"] = _times(lambda i: syn(xt[i % n: i % n + 1]), max(args.reps // 3, 20))
            torch.set_num_threads(1)
            torch_res["batch32_threads1"] = _throughput(lambda i: syn(xt[starts[i % len(starts)]:][:32]), args.reps32, 32)
        entry["torch_eager"] = torch_res
        out["regressors"][name] = entry
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
