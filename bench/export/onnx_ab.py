"""Interleaved A/B timing of exported synthesis models (same landmarks, same machine state).

Each file gets its own ONNX Runtime session with the :class:`facesynth.runtime.Renderer`
settings (one intra-op thread, sequential, no spinning); rounds of ``--reps`` batch-1 runs
alternate between the files, so that load from other processes hits every file alike.
Reports per file the median wall and thread-CPU time (ms) over all runs, the best round's
median, the minimum, and whether every output equals the first file's (bit for bit) on
all the landmarks used.

    python -m bench.export.onnx_ab A.onnx B.onnx --landmarks L.npy [--rounds 10] [--reps 100]

``--landmarks``: (N, P, 2) float32 frame landmarks in the models' scheme (e.g. a clip's
``landmarks.npy``). Prints ONE JSON line.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort

from bench.harness import emit, load_averages


def _session(path: str) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def interleaved_times(sessions, lm: np.ndarray, rounds: int, reps: int) -> tuple[list, list]:
    """Batch-1 wall and thread-CPU seconds per session, (rounds, reps) each: rounds of ``reps``
    runs alternate between the sessions after 50 warm-up runs each."""
    name = sessions[0].get_inputs()[0].name
    for s in sessions:  # warm-up
        for i in range(50):
            s.run(None, {name: lm[i % len(lm):i % len(lm) + 1]})
    wall = [[] for _ in sessions]
    cpu = [[] for _ in sessions]
    for _ in range(rounds):
        for j, s in enumerate(sessions):
            w, c = [], []
            for i in range(reps):
                k = (i * 7) % len(lm)
                t0, c0 = time.perf_counter(), time.thread_time()
                s.run(None, {name: lm[k:k + 1]})
                c.append(time.thread_time() - c0)
                w.append(time.perf_counter() - t0)
            wall[j].append(w)
            cpu[j].append(c)
    return wall, cpu


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+")
    p.add_argument("--landmarks", required=True)
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--reps", type=int, default=100)
    args = p.parse_args()
    load_start = load_averages()
    lm = np.ascontiguousarray(np.load(args.landmarks), np.float32)
    lm = lm[np.isfinite(lm).all(axis=(1, 2))]
    sessions = [_session(m) for m in args.models]
    name = sessions[0].get_inputs()[0].name
    ref = [sessions[0].run(None, {name: lm[i:i + 8]}) for i in range(0, len(lm), 8)]
    same = [all(all(np.array_equal(a, b) for a, b in zip(r, s.run(None, {name: lm[i * 8:i * 8 + 8]}), strict=True))
                for i, r in enumerate(ref)) for s in sessions]
    wall, cpu = interleaved_times(sessions, lm, args.rounds, args.reps)
    out = {"bench": "onnx_ab", "loadavg_at_start": load_start, "loadavg_at_end": load_averages(),
           "frames": int(len(lm)), "rounds": args.rounds, "reps": args.reps, "models": {}}
    for m, w, c, eq in zip(args.models, wall, cpu, same, strict=True):
        w, c = np.asarray(w) * 1e3, np.asarray(c) * 1e3
        out["models"][m] = {"wall_ms_p50": round(float(np.median(w)), 4), "cpu_ms_p50": round(float(np.median(c)), 4),
                            "wall_ms_best_round_p50": round(float(np.median(w, 1).min()), 4),
                            "wall_ms_min": round(float(w.min()), 4), "outputs_equal_first": bool(eq)}
    emit(out)
if __name__ == "__main__":
    main()
