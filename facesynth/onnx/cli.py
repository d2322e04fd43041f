"""``facesynth export RUN --out model.onnx``: one ONNX file from a training run (the export
API: :mod:`facesynth.onnx.export`; the options: :class:`facesynth.onnx.config.ExportConfig`).
Prints one line (what was written, its size, its check), or the summary as JSON with ``--json``."""

from __future__ import annotations

import argparse

from facesynth import progress
from facesynth.onnx.config import add_arguments, from_args

__all__ = ["add_arguments", "run"]


def run(args: argparse.Namespace) -> int:
    from facesynth.onnx.export import export, summary_line  # lazy: keeps --help fast (torch)

    summary = export(from_args(args))
    progress.result(summary_line(summary), summary)
    return 0
