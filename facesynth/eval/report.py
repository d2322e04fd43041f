"""Evaluation reports: ``report.md`` plus plots (matplotlib, Agg backend)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.io import atomic_path, write_text


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    _plt().close(fig)


def write_plots(metrics: dict, extras: dict, out_dir: str | os.PathLike) -> list[str]:
    """Write PSNR-vs-noise, NCC bars, real-vs-synthesized grid and error heat-map PNGs."""
    plt = _plt()
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    written = []
    fig, axes = plt.subplots(1, 2 if "psnr_frame" in metrics else 1, figsize=(10, 3.5), squeeze=False)
    for ax, key, title in zip(axes[0], ("psnr_ref", "psnr_frame"), ("reference frame", "original frame"), strict=False):
        for name, row in metrics.get(key, {}).items():
            xs = [float(k) for k in row]
            ax.plot(xs, list(row.values()), marker="o", label=name)
        ax.set(xlabel="landmark noise sigma (px)", ylabel="PSNR (dB)", title=f"test PSNR, {title}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    _save(fig, d / "psnr_vs_noise.png")
    written.append("psnr_vs_noise.png")
    fig, ax = plt.subplots(figsize=(10, 3))
    ncc = metrics.get("ncc", [])
    ax.bar(np.arange(1, len(ncc) + 1), ncc, color="tab:blue")
    ax.set(xlabel="appearance component", ylabel="NCC", title="predicted vs true b_g on test frames", ylim=(-0.2, 1))
    _save(fig, d / "ncc.png")
    written.append("ncc.png")
    if extras.get("err_map") is not None:
        fig, ax = plt.subplots(figsize=(4, 4))
        im = ax.imshow(extras["err_map"], cmap="inferno")
        ax.set_title("test MSE per pixel (reference frame, sigma 0)")
        ax.axis("off")
        fig.colorbar(im, ax=ax, fraction=0.046)
        _save(fig, d / "error_map.png")
        written.append("error_map.png")
    grid = extras.get("grid") or []
    if grid:
        fig, axes = plt.subplots(2, len(grid), figsize=(2.2 * len(grid), 4.6), squeeze=False)
        for i, (real, synth) in enumerate(grid):
            axes[0, i].imshow(real)
            axes[1, i].imshow(synth)
            axes[0, i].axis("off")
            axes[1, i].axis("off")
        axes[0, 0].set_title("real (test)", fontsize=9, loc="left")
        axes[1, 0].set_title("synthesized from landmarks", fontsize=9, loc="left")
        _save(fig, d / "test_grid.png")
        written.append("test_grid.png")
    return written


def _table(block: dict) -> list[str]:
    keys = list(next(iter(block.values())).keys())
    lines = ["| row | " + " | ".join(f"sigma {k}" for k in keys) + " |", "|---|" + "---|" * len(keys)]
    for name, row in block.items():
        lines.append(f"| {name} | " + " | ".join(f"{row[k]:.2f}" for k in keys) + " |")
    return lines


def write_report(metrics: dict, out_dir: str | os.PathLike, plots: list[str], header: dict | None = None) -> None:
    """Write ``report.md`` summarising ``metrics`` with the plots."""
    lines = [f"# facesynth run: {metrics.get('regressor')} regressor", ""]
    for k, v in (header or {}).items():
        lines.append(f"- **{k}**: {v}")
    lines += [
        f"- shape components: {metrics['n_shape']}, appearance components: {metrics['n_appearance']}",
        f"- frames: {metrics['train_frames']} train / {metrics['test_frames']} test (temporal split)",
        "",
        "## Test PSNR in the reference frame (dB, peak 255, over the face mask)",
        "",
        *_table(metrics["psnr_ref"]),
    ]
    if "psnr_frame" in metrics:
        lines += ["", "## Test PSNR in the original frame (dB, whole pipeline, face region)", "", *_table(metrics["psnr_frame"])]
    if "psnr_train_ref" in metrics:
        lines += ["", "## Training-frame PSNR in the reference frame (the paper's Table 2 setting)", "", *_table(metrics["psnr_train_ref"])]
    ncc = np.asarray(metrics.get("ncc", []))
    if ncc.size:
        lines += ["", "## Per-component NCC of predicted vs true b_g (test frames)", "",
                  f"first 10: {', '.join(f'{v:.2f}' for v in ncc[:10])}; mean over all {ncc.size}: {ncc.mean():.3f}"]
    lines += ["", "## Plots", ""] + [f"![{p}](plots/{p})" for p in plots]
    write_text(Path(out_dir) / "report.md", "\n".join(lines) + "\n")
