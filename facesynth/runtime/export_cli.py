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


def run(args: argparse.Namespace) -> int:
    from facesynth.export_onnx import check_export, export_synthesizer, load_synthesizer

    syn, meta = load_synthesizer(args.run)
    path = export_synthesizer(syn, args.out, meta, args.opset)
    summary = {"out": str(path), "bytes": path.stat().st_size, **meta, "opset": args.opset}
    if not args.no_check:
        summary["max_abs_diff_vs_torch"] = check_export(syn, path)
    print(json.dumps(summary))
    return 0
