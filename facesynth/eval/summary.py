"""A run's figures as console lines (``facesynth train`` and ``facesynth evaluate`` print them)."""

from __future__ import annotations

import numpy as np

from facesynth.eval.report import legend_lines


def summary_lines(metrics: dict) -> list[str]:
    """Short printable summary of a metrics dict."""
    lines = [f"regressor={metrics['regressor']} shape={metrics['n_shape']} appearance={metrics['n_appearance']} "
             f"train={metrics['train_frames']} test={metrics['test_frames']}"]
    for key in ("psnr_ref", "psnr_frame", "psnr_frame_common", "psnr_train_ref"):
        if key in metrics:
            for row, vals in metrics[key].items():
                lines.append(f"{key:15s} {row:13s} " + "  ".join(f"s{k}={v:6.2f}" for k, v in vals.items()))
    lines.append(f"ncc mean={np.mean(metrics['ncc']):.3f} (first 5: {', '.join(f'{v:.2f}' for v in metrics['ncc'][:5])})")
    fl = metrics.get("frame_level_frames")
    if fl:
        lines.append(f"psnr_frame on {fl['evaluated']} of {fl['test_frames']} test frames (evenly spaced; eval.max_test_frames)")
    return lines + ["legend:"] + [f"  {line}" for line in legend_lines()]
