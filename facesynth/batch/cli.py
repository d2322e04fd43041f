"""``facesynth batch VIDEOS_DIR_OR_GLOB --out DIR [overrides]``: many subjects at once.

Every video becomes ``DIR/<subject>/`` (ingest folder ``data/``, ``run/``, ``model.onnx``, its log);
``DIR/summary.csv``, ``summary.md``, ``summary.json`` and ``summary.png`` cover them all.
Runs on Ray when it is installed (the ``batch`` extra), one subject after another otherwise.
Exit status: 0 when every subject is complete, 1 when some failed (see the summary), 2 on
bad arguments.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import signal
import sys
from pathlib import Path

from facesynth.errors import FacesynthError
from facesynth.progress import result

# facesynth.cli parses this subcommand's arguments intermixed: overrides may follow options.
INTERMIXED_ARGS = True

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from facesynth.batch.state import LANDMARKERS

    p.description = (
        "For each video: ingest (dlib landmarks) -> train + evaluate (as train.py, with the default "
        "configuration or the overrides) -> export (ONNX), each subject in DIR/<subject>/, then "
        "DIR/summary.csv, summary.md, summary.json and summary.png. A failing subject is reported "
        "and the others go on; a re-run skips the stages whose outputs are complete and valid. "
        "Runs on Ray (pip install 'facesynth[batch]'): a local runtime using this machine's cores, "
        "or a cluster with --address / $RAY_ADDRESS; without Ray, one subject after another."
    )
    p.add_argument("videos", metavar="VIDEOS_DIR_OR_GLOB",
                   help="a folder (searched recursively for videos), a quoted glob pattern, or one video")
    p.add_argument("overrides", nargs="*", metavar="OVERRIDE",
                   help="Hydra-style overrides of the training config, as train.py takes them "
                        "(e.g. regressor=linear eval.frame_level=false)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (one sub-folder per subject)")
    p.add_argument("--regressor", help="the SADM regressor (same as the override regressor=NAME; default: the config's)")
    p.add_argument("--landmarker", choices=sorted(LANDMARKERS), default="dlib", help="face landmarker for ingest (default dlib)")
    p.add_argument("--max-frames", type=int, metavar="N", help="ingest only the first N frames of each video")
    p.add_argument("--every", type=int, default=1, metavar="N", help="ingest every N-th frame (default 1)")
    p.add_argument("--min-frames", type=int, default=30, metavar="N",
                   help="a subject with fewer frames with a face fails as too short (default 30)")
    p.add_argument("--components", type=int, default=None, help="export: appearance components kept (as facesynth export)")
    p.add_argument("--basis", choices=["int8", "float32"], default="int8", help="export: appearance basis storage (default int8)")
    ray = p.add_argument_group("execution (Ray)")
    ray.add_argument("--address", help="Ray cluster to run on (ray://HOST:10001 or HOST:PORT; default $RAY_ADDRESS, "
                                       "else a local Ray runtime on this machine)")
    ray.add_argument("--workers", type=int, metavar="N",
                     help="local runtime: subjects run at once (default: cores / --cpus-per-subject)")
    ray.add_argument("--cpus-per-subject", type=int, metavar="C",
                     help="CPUs each subject asks for; torch and OpenCV use that many threads "
                          "(default: 1 on a cluster; cores / --workers locally)")
    ray.add_argument("--memory-per-subject", type=float, metavar="MB",
                     help="memory each subject asks for (default: estimated from its frame count)")
    ray.add_argument("--retries", type=int, default=1, help="Ray retries of a subject whose worker died (default 1)")
    ray.add_argument("--sequential", action="store_true", help="no Ray: run the subjects one after another here")


def _check(args: argparse.Namespace) -> None:
    for name in ("max_frames", "every", "min_frames", "workers", "cpus_per_subject", "memory_per_subject"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise FacesynthError(f"--{name.replace('_', '-')} must be >= 1, got {v}")
    if args.components is not None and args.components < 0:
        raise FacesynthError(f"--components must be >= 0, got {args.components}")
    if args.retries < 0:
        raise FacesynthError(f"--retries must be >= 0, got {args.retries}")
    if args.out.exists() and not args.out.is_dir():
        raise FacesynthError(f"{args.out}: exists and is not a folder")


def training_config(overrides: list[str], regressor: str | None) -> dict:
    """The composed training config (a container) every subject trains with."""
    from omegaconf import OmegaConf

    from facesynth.runs.config import compose_config

    base = ["data=video"] + ([f"regressor={regressor}"] if regressor else [])
    cfg = compose_config(base + list(overrides))
    if cfg.data.kind != "video" or cfg.model.kind != "aam":
        raise FacesynthError("batch trains SADM models on the videos: do not override data= or model.kind "
                             f"(got data.kind={cfg.data.kind}, model.kind={cfg.model.kind})")
    cfg.data.path = "<subject folder>"
    return OmegaConf.to_container(cfg, resolve=True)


def make_jobs(args: argparse.Namespace, config: dict) -> list:
    from facesynth.batch import state
    from facesynth.batch.discover import find_videos, subject_names
    from facesynth.batch.job import SubjectJob
    from facesynth.contract import OPSET
    from facesynth.onnx.config import DEFAULT_COMPONENTS

    videos = find_videos(args.videos)
    export = {"opset": OPSET, "components": DEFAULT_COMPONENTS if args.components is None else args.components,
              "basis": args.basis}
    out = args.out.resolve()
    jobs = []
    for video, name in zip(videos, subject_names(videos), strict=True):
        cfg = json.loads(json.dumps(config))
        cfg["data"]["path"] = str(out / name / state.DATA_DIR)
        jobs.append(SubjectJob(name=name, video=os.path.abspath(video), out=str(out / name), config=cfg, export=export,
                               every=args.every, max_frames=args.max_frames, landmarker=args.landmarker,
                               min_frames=args.min_frames))
    return jobs


def _execute(args: argparse.Namespace, jobs: list, progress) -> tuple[list[dict], str]:
    from facesynth.batch import executor

    use_ray = not args.sequential and executor.ray_available()
    if not use_ray:
        if args.address and not args.sequential:
            raise FacesynthError("--address needs Ray: pip install 'facesynth[batch]'")
        why = "--sequential" if args.sequential else "Ray is not installed (pip install 'facesynth[batch]')"
        print(f"{why}: running the {len(jobs)} subjects one after another", file=sys.stderr)
        return executor.run_sequential(jobs, progress), "sequential"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    remote = bool(args.address or os.environ.get("RAY_ADDRESS"))
    workers = args.workers or max(1, cores // (args.cpus_per_subject or 1))
    cpus = args.cpus_per_subject or (1 if remote else max(1, cores // workers))
    started, where = executor.start_ray(args.address, None if remote else workers * cpus)
    try:
        frames = [executor.video_frames(j.video, j.every, j.max_frames) for j in jobs]
        memory = [int(args.memory_per_subject * 2**20) if args.memory_per_subject else executor.memory_request(f)
                  for f in frames]
        print(f"{where}: {len(jobs)} subjects, {cpus} CPU and {max(memory) / 2**30:.1f} GiB at most "
              "requested per subject", file=sys.stderr)
        jobs = [dataclasses.replace(j, threads=cpus) for j in jobs]
        return executor.run_ray(jobs, progress, cpus=cpus, memory=memory, retries=args.retries), where
    finally:
        if started:
            import ray

            ray.shutdown()


def run(args: argparse.Namespace) -> int:
    import time

    from facesynth.batch.executor import Progress
    from facesynth.batch.summary import counts, write_summary

    _check(args)
    config = training_config(args.overrides, args.regressor)
    jobs = make_jobs(args, config)
    t0 = time.perf_counter()
    progress = Progress(len(jobs), enabled=not args.quiet)
    # SIGTERM (a scheduler cancelling the driver) unwinds like Ctrl-C: Ray tasks cancelled, Ray shut down.
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    try:
        rows, where = _execute(args, jobs, progress)
    finally:
        signal.signal(signal.SIGTERM, previous)
        progress.close()
    wall = time.perf_counter() - t0
    paths = write_summary(rows, args.out)
    c = counts(rows)
    for r in rows:
        if r["status"] == "failed":
            print(f"failed: {r['subject']}: {r['reason']}", file=sys.stderr)
    result(f"{len(rows)} subjects in {wall:.1f} s on {where}: {c['ok']} trained, {c['skipped']} already complete, "
           f"{c['failed']} failed -> {paths['csv']}, {paths['md'].name}, {paths['png'].name}",
           {"subjects": len(rows), **c, "wall_s": round(wall, 3), "executor": where, "summary": str(paths["csv"])})
    return 1 if c["failed"] else 0
