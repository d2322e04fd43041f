"""Runtime benchmark: exported synthesis models in ONNX Runtime vs torch eager.

Fits a face model on a real clip (default lp_d6, every 2nd frame), fits every registered
SADM regressor on it with the settings of ``train.py regressor=NAME`` (``train_defaults``), exports each three times --
``uncompressed`` (every component, float32 basis), ``compressed`` (the export's appearance
compression, ``--components``, default the export default 40: the components of largest
predicted variance over the training landmarks, the rest folded into the mean; float32
basis) and ``default`` (what ``facesynth export`` writes: compressed, and the basis in int8,
:mod:`facesynth.sadm.quantize`) -- and measures, at the model's reference size:

* per-frame latency at batch 1 with 1 and 2 threads (median and p90 wall clock, and the
  median CPU time of the calling process, which is less affected by other load; also the
  best of the medians of 10 consecutive rounds, the figure least affected by other jobs);
* throughput at batch 32 (frames/s, 1 thread);
* the same for torch eager (``Synthesizer.forward``, ``torch.set_num_threads``);
* model file size, support vectors (SVR), appearance components, peak RSS;
* the compression's and the int8 basis' effect: PSNR of the compressed vs the full and of
  the int8 vs the float32 texture over the training landmarks (the figures the export
  records), and the held-out texture PSNR (odd frames, which the model never saw) of every
  variant against the real textures.

``summary`` repeats the headline: batch-1 one-thread frames/s (wall, CPU, best round) of the
default export per regressor.

Both landmark schemes in one run: ``--dense DIR`` (a folder that ``facesynth ingest
--landmarker mediapipe`` wrote, e.g. of the same clip) measures a ``mediapipe478`` model
too, under ``schemes.mediapipe478`` (same settings), and ``summary`` becomes
``{scheme: {regressor: frames/s}}``. ``--variants default``, ``--no-torch`` and ``--max-epochs`` shorten a run.

Prints ONE JSON line.

    python -m bench.runtime.runtime [--regressors linear,mlp] [--components 40] [--reps 1000]
    python -m bench.runtime.runtime --regressors linear,mlp --variants default --no-torch --dense /tmp/mp/lp_d6
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

from bench.harness import emit, load_averages

ROUNDS = 10  # repetitions are split into this many rounds; the best round median is reported too


def _times(fn, reps: int, warmup: int = 5) -> dict:
    """Median / p90 wall clock and median CPU time (ms) over ``reps`` calls, and the best
    (smallest) of the medians of ``ROUNDS`` consecutive rounds (less affected by other load)."""
    for _ in range(warmup):
        fn(0)
    wall, cpu = [], []
    for i in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn(i)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    w, c = np.asarray(wall) * 1e3, np.asarray(cpu) * 1e3
    rounds = max(1, min(ROUNDS, reps // 20))
    best_w = min(float(np.median(r)) for r in np.array_split(w, rounds))
    best_c = min(float(np.median(r)) for r in np.array_split(c, rounds))
    return {"wall_ms_p50": round(float(np.median(w)), 4), "wall_ms_p90": round(float(np.percentile(w, 90)), 4),
            "cpu_ms_p50": round(float(np.median(c)), 4), "wall_ms_best_round_p50": round(best_w, 4),
            "cpu_ms_best_round_p50": round(best_c, 4), "rounds": rounds}


def _throughput(fn, reps: int, batch: int) -> dict:
    t = _times(fn, reps, warmup=2)
    return {"batch": batch, "frames_per_s_wall": round(batch / t["wall_ms_p50"] * 1e3, 1),
            "frames_per_s_cpu": round(batch / t["cpu_ms_p50"] * 1e3, 1)}


def _measure(syn, path, lm, reps: int, reps32: int, with_torch: bool = True) -> dict:
    """ONNX Runtime and torch eager figures of one exported model."""
    import torch

    from facesynth.runtime import Renderer

    n = len(lm)
    res: dict = {"onnx_bytes": path.stat().st_size}
    ort_res = {}
    for threads in (1, 2):
        r = Renderer(path, threads=threads)
        ort_res[f"batch1_threads{threads}"] = _times(lambda i, r=r: r.render(lm[i % n: i % n + 1]), reps)
    r = Renderer(path, threads=1)
    starts = np.arange(0, n - 32, 32)
    ort_res["batch32_threads1"] = _throughput(lambda i: r.render(lm[starts[i % len(starts)]:][:32]), reps32, 32)
    for t in (1, 2):
        b = ort_res[f"batch1_threads{t}"]
        ort_res[f"frames_per_s_batch1_threads{t}"] = {
            "wall": round(1e3 / b["wall_ms_p50"], 1), "cpu": round(1e3 / b["cpu_ms_p50"], 1),
            "wall_best_round": round(1e3 / b["wall_ms_best_round_p50"], 1), "cpu_best_round": round(1e3 / b["cpu_ms_best_round_p50"], 1)}
    res["onnxruntime"] = ort_res
    if not with_torch:
        return res
    torch_res = {}
    xt = torch.from_numpy(lm)
    with torch.no_grad():
        for threads in (1, 2):
            torch.set_num_threads(threads)
            torch_res[f"batch1_threads{threads}"] = _times(lambda i: syn(xt[i % n: i % n + 1]), max(reps // 3, 20))
        torch.set_num_threads(1)
        torch_res["batch32_threads1"] = _throughput(lambda i: syn(xt[starts[i % len(starts)]:][:32]), reps32, 32)
    res["torch_eager"] = torch_res
    return res


def _heldout_psnr(syn, lm, textures) -> float:
    """Texture PSNR (dB, peak 1, pooled) of ``syn``'s prediction vs real (N, C*M) textures."""
    import torch

    with torch.no_grad():
        pred = syn.texture(torch.from_numpy(lm)).double().numpy().reshape(len(lm), -1)
    mse = float(np.mean((pred - textures) ** 2))
    return round(10 * np.log10(1.0 / mse), 3)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", default="lp_d6")
    p.add_argument("--step", type=int, default=2, help="training rows: every STEP-th frame")
    p.add_argument("--n-appearance", type=int, default=None, help="appearance components (default: the model default)")
    p.add_argument("--components", type=int, default=None, help="components kept by the compressed export (default: export default)")
    p.add_argument("--regressors", default="", help="comma-separated names (default: every registered one)")
    p.add_argument("--reps", type=int, default=1000,
                   help="batch-1 repetitions per setting (about a second each: a median robust to shorter bursts of other load)")
    p.add_argument("--reps32", type=int, default=20, help="batch-32 repetitions")
    p.add_argument("--variants", default="uncompressed,compressed,default", help="export variants to measure")
    p.add_argument("--no-torch", action="store_true", help="skip the torch eager figures")
    p.add_argument("--dense", type=Path, help="a mediapipe478 ingest folder: measure that scheme too, same settings")
    p.add_argument("--max-epochs", type=int, help="cap the MLP's training epochs (speed does not depend on them)")
    args = p.parse_args(argv)

    from facesynth.data import load_sequence, shared_clip

    clip = shared_clip(args.clip)
    if clip is None:
        print(json.dumps({"error": f"shared clip {args.clip!r} is absent"}))
        return 2
    start = {"bench": "runtime", "clip": args.clip, "cpu_count": os.cpu_count(),
             "loadavg_at_start": load_averages()}
    out = {**start, **_bench_clip(load_sequence(clip), args)}
    if args.dense is not None:
        dense = _bench_clip(load_sequence(args.dense), args)
        out = {**start, "schemes": {"ibug68": out, dense["landmark_scheme"]: dense},
               "summary": {"ibug68": out["summary"], dense["landmark_scheme"]: dense["summary"]}}
    out["loadavg_at_end"] = load_averages()
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    emit(out)
    return 0


def _bench_clip(seq, args) -> dict:
    """Every figure of one sequence (its own landmark scheme)."""
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.onnx.config import DEFAULT_COMPONENTS
    from facesynth.onnx.synthesis import compress_for_export, export_synthesizer, quantize_for_export
    from facesynth.regressors import REGISTRY
    from facesynth.runs.config import train_defaults
    from facesynth.sadm.fit import fit_sadm

    rows = np.arange(0, len(seq), args.step)
    held = np.setdiff1d(np.arange(len(seq)), rows)
    t0 = time.perf_counter()
    model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(n_appearance=args.n_appearance), rows=rows, progress=False)
    fit_s = time.perf_counter() - t0
    tex_held = model.sample_textures(seq, held).astype(np.float64)
    lm = seq.landmarks.astype(np.float32)
    train_lm = lm[rows]
    keep = DEFAULT_COMPONENTS if args.components is None else args.components
    names = [s for s in args.regressors.split(",") if s] or sorted(REGISTRY)
    variants = [v for v in args.variants.split(",") if v]
    out = {
        "landmark_scheme": seq.scheme, "n_landmarks": int(seq.landmarks.shape[1]),
        "train_frames": int(len(rows)), "heldout_frames": int(len(held)),
        "reference_size": list(model.reference.size), "n_shape": model.shape_pca.n_components,
        "n_appearance": model.appearance_pca.n_components, "n_triangles": model.reference.n_triangles,
        "components_kept": keep, "model_fit_s": round(fit_s, 1), "summary": {}, "regressors": {},
    }
    with tempfile.TemporaryDirectory(prefix="bench_runtime_") as tmp_dir:  # the exported files are removed
        tmp = Path(tmp_dir)
        for name in names:
            entry: dict = {}
            t0 = time.perf_counter()
            rname, params, sadm_cfg = train_defaults(name)  # as train.py regressor=NAME
            if args.max_epochs and "max_epochs" in params:
                params = {**params, "max_epochs": args.max_epochs}
            sadm = fit_sadm(model, seq, rows, tex, rname, params, sadm_cfg)
            entry["fit_s"] = round(time.perf_counter() - t0, 2)
            entry["summary"] = sadm.regressor.summary()
            syn = sadm.synthesizer()
            small, info = compress_for_export(syn, train_lm, keep)
            default, q_info = quantize_for_export(small, train_lm)
            for tag, s_ in (("uncompressed", syn), ("compressed", small), ("default", default)):
                if tag not in variants:
                    continue
                path = export_synthesizer(s_, tmp / f"{name}_{tag}.onnx", {"data_fingerprint": model.fingerprint})
                res = {"appearance_components": int(s_.appearance.components.shape[0]),
                       "appearance_basis": "float32" if s_.appearance.basis is None else "int8",
                       "heldout_texture_psnr_db": _heldout_psnr(s_, lm[held], tex_held)}
                res.update(_measure(s_, path, lm, args.reps, args.reps32, not args.no_torch))
                entry[tag] = res
            entry["compression"] = {k: v for k, v in info.items() if k != "kept_components"}
            entry["quantization"] = q_info
            out["regressors"][name] = entry
            out["summary"][name] = entry[variants[-1]]["onnxruntime"]["frames_per_s_batch1_threads1"]
    return out


if __name__ == "__main__":
    sys.exit(main())
