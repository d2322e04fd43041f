"""Plots of a SADM run (matplotlib, Agg backend): PSNR vs landmark noise, per-component NCC,
PSNR over time across the test segment, the test grid and the error heat-map."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.io import atomic_path

N_WORST = 3  # worst frames marked on the PSNR-over-time plot


def pyplot():
    """matplotlib.pyplot with the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | os.PathLike, dpi: int = 110) -> None:
    """Write ``fig`` as PNG atomically and close it."""
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    pyplot().close(fig)


def psnr_vs_noise(metrics: dict, path) -> None:
    plt = pyplot()
    keys = [k for k in ("psnr_ref", "psnr_frame") if k in metrics]
    fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 3.8), squeeze=False)
    titles = {"psnr_ref": "reference frame (face mask)", "psnr_frame": "original frame (whole pipeline)"}
    for ax, key in zip(axes[0], keys, strict=True):
        for name, row in metrics[key].items():
            ax.plot([float(k) for k in row], list(row.values()), marker="o", label=name)
        ax.set(xlabel="landmark noise sigma (frame px)", ylabel="test PSNR (dB)", title=titles[key])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save(fig, path)


def ncc_bars(ncc: list[float], path) -> None:
    plt = pyplot()
    v = np.asarray(ncc, float)
    fig, ax = plt.subplots(figsize=(10, 3.2))
    ax.bar(np.arange(1, len(v) + 1), v, color=np.where(v >= 0, "tab:blue", "tab:red"))
    ax.axhline(0, color="k", lw=0.8)
    if v.size:
        ax.axhline(v.mean(), color="tab:orange", ls="--", lw=1, label=f"mean {v.mean():.3f}")
        ax.legend(fontsize=8, loc="upper right")
    lo = min(-0.05, float(v.min()) - 0.05) if v.size else -0.05
    ax.set(xlabel="appearance component (1 = most variance)", ylabel="NCC", ylim=(lo, 1.02), xlim=(0.3, len(v) + 0.7),
           title="NCC of predicted vs true appearance parameters per component (test frames, sigma 0)")
    ax.grid(axis="y", alpha=0.3)
    save(fig, path)


def psnr_over_time(per_frame: dict, path) -> list[int]:
    """Per-frame test PSNR against the frame number; returns the worst frames marked."""
    plt = pyplot()
    frames = np.asarray(per_frame["frame"])
    ref = np.asarray(per_frame["psnr_ref"])
    fig, ax = plt.subplots(figsize=(10, 3.6))
    ax.plot(frames, ref, lw=1.2, color="tab:blue", label="sadm, reference frame (every test frame)")
    if "psnr_frame" in per_frame:
        idx = np.asarray(per_frame["frame_index"])
        for name, color in (("sadm", "tab:green"), ("rewarp", "tab:gray")):
            if name in per_frame["psnr_frame"]:
                ax.plot(frames[idx], per_frame["psnr_frame"][name], "o-", ms=3, lw=0.8, color=color,
                        label=f"{name}, original frame ({len(idx)} frames evaluated)")
    worst = np.argsort(ref)[:N_WORST]
    listed = ", ".join(f"{frames[w]} ({ref[w]:.1f} dB)" for w in worst)
    ax.scatter(frames[worst], ref[worst], s=80, facecolors="none", edgecolors="red", lw=1.5, zorder=5,
               label=f"worst: {listed}")
    for rank, w in enumerate(worst):
        ax.annotate(str(rank + 1), (frames[w], ref[w]), textcoords="offset points", xytext=(6, 2), fontsize=8, color="red")
    ax.set(xlabel="frame number", ylabel="PSNR (dB), sigma 0", title="test PSNR over time across the test segment")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    save(fig, path)
    return [int(frames[w]) for w in worst]


def test_grid(grid: list[dict], path, gain: float = 4.0) -> None:
    """Rows: real test frame, synthesized from its landmarks, |difference| x ``gain``;
    columns titled with the frame number and its frame-level PSNR."""
    plt = pyplot()
    n = len(grid)
    fig, axes = plt.subplots(3, n, figsize=(3.0 * n, 9.6), squeeze=False)
    for i, g in enumerate(grid):
        diff = np.clip(np.abs(g["real"].astype(np.int16) - g["synth"].astype(np.int16)) * gain, 0, 255).astype(np.uint8)
        for r, img in enumerate((g["real"], g["synth"], diff)):
            axes[r, i].imshow(img)
            axes[r, i].set_xticks([])
            axes[r, i].set_yticks([])
        axes[0, i].set_title(f"frame {g['frame']}\nPSNR {g['psnr']:.2f} dB", fontsize=10)
    for r, label in enumerate(("real (test)", "synthesized", f"|difference| x {gain:g}")):
        axes[r, 0].set_ylabel(label, fontsize=10)
    fig.tight_layout()
    save(fig, path)


def error_map(err: np.ndarray, path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.6, 4.6))
    im = ax.imshow(err, cmap="inferno")
    ax.set_title("test MSE per pixel\n(reference frame, sigma 0)", fontsize=10)
    ax.axis("off")
    fig.colorbar(im, ax=ax, fraction=0.046, label="MSE (8-bit levels^2)")
    save(fig, path)
