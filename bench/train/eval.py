"""Time a run's evaluation (facesynth.eval.sadm_eval.evaluate_sadm) with the default
frame-level subset, optionally against every test frame; prints one JSON line.

    OMP_NUM_THREADS=1 python -m bench.train.eval RUN_DIR [--compare-all]

RUN_DIR is a train.py run (its config names the data and the split). Figures: CPU and wall
seconds of the evaluation, and with --compare-all the largest |difference| (dB) of every
psnr_frame entry between the default subset and every test frame.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from bench.harness import emit
from facesynth import progress  # noqa: E402
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.sadm.fit import load_sadm  # noqa: E402


def _timed(sadm, seq, tr, te, cfg, seed):
    c0, w0 = time.process_time(), time.perf_counter()
    metrics, _ = evaluate_sadm(sadm, seq, tr, te, cfg, seed)
    return metrics, time.process_time() - c0, time.perf_counter() - w0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("--compare-all", action="store_true", help="also evaluate every test frame and compare")
    args = ap.parse_args()
    progress.set_quiet(True)
    cfg = read_config(args.run)
    seq, tr, te = run_data(cfg)
    sadm = load_sadm(args.run)
    m, cpu, wall = _timed(sadm, seq, tr, te, EvalConfig(), int(cfg.seed))
    out = {"run": str(args.run), "data": seq.name, "frame_size": list(seq.frames.size), "test_frames": len(te),
           "frame_level_frames": m["frame_level_frames"]["evaluated"], "eval_cpu_s": round(cpu, 2),
           "eval_wall_s": round(wall, 2), "psnr_frame_sadm": m["psnr_frame"]["sadm"]}
    if args.compare_all:
        m_all, cpu_all, wall_all = _timed(sadm, seq, tr, te, EvalConfig(max_test_frames=None), int(cfg.seed))
        diffs = {f"{row}@{k}": round(abs(m["psnr_frame"][row][k] - m_all["psnr_frame"][row][k]), 4)
                 for row in m["psnr_frame"] for k in m["psnr_frame"][row]}
        out.update(all_eval_cpu_s=round(cpu_all, 2), all_eval_wall_s=round(wall_all, 2),
                   psnr_frame_sadm_all=m_all["psnr_frame"]["sadm"], max_abs_diff_db=max(diffs.values()),
                   abs_diff_db=diffs)
    emit(out)
if __name__ == "__main__":
    main()
