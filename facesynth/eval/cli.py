"""``facesynth evaluate RUN``: re-evaluate a saved training run."""

from __future__ import annotations

import argparse
from pathlib import Path

from facesynth.errors import FacesynthError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, help="training run directory (written by train.py)")
    p.add_argument("--data", type=Path, help="data to evaluate on (default: the run's own data config)")
    p.add_argument("--noise", default="0,1,2,3", help="landmark noise sigmas in frame pixels, comma-separated")
    p.add_argument("--no-frame", action="store_true", help="skip the (slower) whole-frame PSNR")
    p.add_argument("--max-test-frames", type=int, metavar="N",
                   help="whole-frame PSNR on N evenly spaced test frames (default: EvalConfig.max_test_frames, 100; "
                        "0: every test frame)")
    p.add_argument("--common-landmarks", type=Path, metavar="PATH",
                   help="dlib (T, 68, 2) landmarks for psnr_frame_common (default: found as docs/sadm.md says)")
    p.add_argument("--save-json", type=Path, metavar="FILE", help="write the metrics here (JSON)")


def run(args: argparse.Namespace) -> int:
    from facesynth import progress
    from facesynth.eval.common_region import common_landmarks
    from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
    from facesynth.eval.summary import summary_lines
    from facesynth.io import write_json
    from facesynth.rundir import read_config, run_data
    from facesynth.sadm.fit import load_sadm

    sadm = load_sadm(args.run)
    cfg = read_config(args.run)
    if args.data is not None:
        cfg.data.kind, cfg.data.path = "video", str(args.data)
    try:
        noise = [float(s) for s in args.noise.split(",") if s.strip()]
    except ValueError:
        raise FacesynthError(f"--noise: expected comma-separated numbers, got {args.noise!r}") from None
    seq, tr, te = run_data(cfg)
    ecfg = EvalConfig(noise=noise, frame_level=not args.no_frame)
    if args.max_test_frames is not None:
        ecfg.max_test_frames = args.max_test_frames
    ecfg.common_landmarks = str(args.common_landmarks) if args.common_landmarks else None
    common = common_landmarks(seq, ecfg.common_landmarks) if ecfg.frame_level and seq.has_frames else None
    with progress.stage("evaluation"):
        metrics, _ = evaluate_sadm(sadm, seq, tr, te, ecfg, int(cfg.seed), common=common)
    metrics["evaluated_data"] = {"name": seq.name, "fingerprint": seq.fingerprint}
    if args.save_json:
        write_json(args.save_json, metrics)
    saved = [f"metrics -> {args.save_json}"] if args.save_json else []
    progress.result("\n".join(summary_lines(metrics) + saved),  # the run's table: one line per figure row
                    {"run": str(args.run), "psnr_ref": metrics["psnr_ref"], "metrics": args.save_json})
    return 0
