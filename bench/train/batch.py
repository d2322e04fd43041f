"""`facesynth batch` wall time with 1 and with 2 workers on this machine, and per-subject memory.

Prints ONE JSON line.

Default: the same batch (4 shared clips cut to --max-frames, the default training config
unless overrides are given) run as fresh commands on a local Ray runtime with ``--workers 1``
(one subject at a time, with both cores' threads), ``--workers 2`` (two subjects at once, one
thread each) and ``--workers 1 --cpus-per-subject 1`` (serial, one thread); reports the wall
times, the ratios to the 2-worker run, the sum of each stage over subjects (from
summary.json) and the load average around each run.

``--memory``: peak resident memory of one subject job (``facesynth batch --sequential`` on
one clip in a fresh process, read with wait4) at several frame counts, and the line
through them (what MEMORY_BASE_MB / MEMORY_PER_FRAME_MB in facesynth/batch/executor.py hold).

    python -m bench.train.batch [--clips lp_d6,lp_d10,lp_d3,lp_d9] [--max-frames 120] [--keep DIR] [OVERRIDE ...]
    python -m bench.train.batch --memory [--frames 60,300,1008]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.harness import load_average

ROOT = Path(__file__).resolve().parents[2]


def _clips(names: list[str]) -> list[Path]:
    from facesynth.data.shared import shared_clip

    clips = [shared_clip(n) for n in names]
    missing = [n for n, c in zip(names, clips, strict=True) if c is None]
    if missing:
        sys.exit(f"bench_batch: shared clips missing: {missing} (needs ../shared/data)")
    return clips


def _run(cmd: list[str]) -> tuple[float, int, dict]:
    """(wall s, exit status, {peak RSS of the command's own process, stdout}) of one command."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)  # wait4: this child's own rusage
        wall = time.perf_counter() - t0
        proc.returncode = rc = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text, errors = out.read(), err.read()
    if rc not in (0, 1):
        sys.exit(f"bench_batch: {' '.join(cmd)} failed ({rc}):\n{errors[-3000:]}")
    return wall, rc, {"maxrss_mb": usage.ru_maxrss / 1024, "out": text}


def timing(args: argparse.Namespace) -> dict:
    clips = _clips(args.clips.split(","))
    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    try:
        videos = tmp / "videos"
        videos.mkdir()
        for c in clips:
            (videos / f"{c.name}.mp4").symlink_to(c / "video.mp4")
        result: dict = {"clips": [c.name for c in clips], "max_frames": args.max_frames, "overrides": args.overrides,
                        "cores": len(os.sched_getaffinity(0))}
        # (name, workers, CPUs per subject): 1 worker with both cores' threads, 2 workers with one
        # thread each, and 1 worker with one thread (the serial one-thread baseline)
        for key, workers, cpus in (("workers_1", 1, 2), ("workers_2", 2, 1), ("workers_1_one_thread", 1, 1)):
            out = tmp / key
            cmd = [sys.executable, "-m", "facesynth", "batch", str(videos), "--out", str(out), "--workers", str(workers),
                   "--cpus-per-subject", str(cpus), "--max-frames", str(args.max_frames), "--no-progress", *args.overrides]
            load_before = load_average()
            wall, _, _ = _run(cmd)
            rows = json.loads((out / "summary.json").read_text())
            failed = [r["subject"] for r in rows if r["status"] != "ok"]
            if failed:
                sys.exit(f"bench_batch: subjects did not complete in {key}: {failed}")
            stages = {k: round(sum(r[k] for r in rows), 2) for k in ("ingest_s", "train_s", "evaluate_s", "export_s")}
            # the 1-minute load average before and after: other processes on the machine count too
            result[key] = {"wall_s": round(wall, 2), "stage_sums_s": stages,
                                            "loadavg_1m": [round(load_before, 2), round(load_average(), 2)],
                                            "subject_wall_sum_s": round(sum(r["wall_s"] for r in rows), 2),
                                            "psnr_sadm": {r["subject"]: round(r["psnr_sadm"], 3) for r in rows}}
        result["ratio_1_over_2"] = round(result["workers_1"]["wall_s"] / result["workers_2"]["wall_s"], 3)
        result["ratio_1_one_thread_over_2"] = round(result["workers_1_one_thread"]["wall_s"] / result["workers_2"]["wall_s"], 3)
        if args.keep:  # the summary files of the 2-worker run
            args.keep.mkdir(parents=True, exist_ok=True)
            for f in sorted((tmp / "workers_2").glob("summary.*")):
                shutil.copy(f, args.keep / f"batch_{f.name}")
        return result
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def memory(args: argparse.Namespace) -> dict:
    (clip,) = _clips([args.memory_clip])
    tmp = Path(tempfile.mkdtemp(prefix="bench_batch_mem_"))
    try:
        points = []
        for n in [int(s) for s in args.frames.split(",")]:
            cmd = [sys.executable, "-m", "facesynth", "batch", str(clip / "video.mp4"), "--out", str(tmp / f"f{n}"),
                   "--sequential", "--max-frames", str(n), "--no-progress", *args.overrides]
            wall, _, usage = _run(cmd)
            points.append({"frames": n, "peak_rss_mb": round(usage["maxrss_mb"], 1), "wall_s": round(wall, 2)})
        f = np.array([p["frames"] for p in points], float)
        m = np.array([p["peak_rss_mb"] for p in points], float)
        slope, base = np.polyfit(f, m, 1) if len(points) > 1 else (0.0, m[0])
        return {"clip": clip.name, "overrides": args.overrides, "points": points,
                "fit_base_mb": round(float(base), 1), "fit_mb_per_frame": round(float(slope), 3)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", help="training config overrides passed to facesynth batch")
    p.add_argument("--clips", default="lp_d6,lp_d10,lp_d3,lp_d9")
    p.add_argument("--max-frames", type=int, default=120)
    p.add_argument("--keep", type=Path, metavar="DIR", help="copy the 2-worker run's summary files here (batch_summary.*)")
    p.add_argument("--memory", action="store_true", help="measure peak memory per subject instead of the timing")
    p.add_argument("--memory-clip", default="lp_d6")
    p.add_argument("--frames", default="60,300,1008", help="--memory: frame counts")
    args = p.parse_intermixed_args()
    print(json.dumps(memory(args) if args.memory else timing(args)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
