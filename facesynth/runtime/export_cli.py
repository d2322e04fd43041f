"""``facesynth export RUN --out model.onnx``: one ONNX file from a training run.

The export code is torch-side (:mod:`facesynth.export_onnx`, imported only when this
subcommand runs); the written model is checked once with ONNX Runtime against torch.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="training run directory (face_model/ and sadm/regressor.*)")
    p.add_argument("--out", required=True, help="output .onnx file (written atomically)")
    p.add_argument("--opset", type=int, default=18, help="ONNX opset (default 18)")
    p.add_argument("--no-check", action="store_true", help="skip the ONNX Runtime vs torch check")
    p.add_argument("--components", type=int, default=None,
                   help="appearance components kept: those of largest predicted variance over the training "
                        "landmarks, the rest folded into the mean (default 40; 0 = all, no compression)")
    p.add_argument("--predicted-variance", type=float, default=None,
                   help="instead of --components: keep the fewest components holding this fraction of the predicted variance")
    p.add_argument("--landmarks", default=None,
                   help="training landmarks (.npy (N, 68, 2)) for the compression (default: reloaded from RUN/config.yaml)")


def run(args: argparse.Namespace) -> int:
    from facesynth.export_onnx import DEFAULT_COMPONENTS, check_export, export_run

    lm = None
    if args.landmarks:
        from facesynth.data import load_landmarks

        lm = load_landmarks(args.landmarks)
    comps = DEFAULT_COMPONENTS if args.components is None else args.components
    path, syn, meta = export_run(args.run, args.out, args.opset, comps, args.predicted_variance, lm)
    summary = {"out": str(path), "bytes": path.stat().st_size, **meta, "opset": args.opset}
    if not args.no_check:
        summary["max_abs_diff_vs_torch"] = check_export(syn, path)
    print(json.dumps(summary))
    return 0
