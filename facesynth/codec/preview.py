"""``--preview PNG``: a decoded geometry image beside the original and their error."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.io import atomic_path


def write_preview(original: np.ndarray, decoded: np.ndarray, mask: np.ndarray | None, path: str | os.PathLike,
                  frame: int = 0, title: str = "") -> dict:
    """PNG of one frame: original and decoded uint16 geometry images (x, y, z as RGB,
    stretched to the frame's range) and the per-pixel error magnitude (in 16-bit levels,
    over ``mask``). Returns the frame's max and RMS error (16-bit levels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    o = original[frame].astype(np.float64)
    d = decoded[frame].astype(np.float64)
    m = np.ones(o.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    lo, hi = o[m].min(0), o[m].max(0)
    show = lambda x: np.clip((x - lo) / np.maximum(hi - lo, 1), 0, 1) * m[..., None]  # noqa: E731
    err = np.linalg.norm(d - o, axis=-1) * m
    fig, ax = plt.subplots(1, 3, figsize=(12, 4.4))
    ax[0].imshow(show(o))
    ax[0].set_title(f"original, frame {frame}")
    ax[1].imshow(show(d))
    ax[1].set_title("decoded")
    im = ax[2].imshow(err, cmap="magma")
    rms = float(np.sqrt((err[m] ** 2).mean())) if m.any() else 0.0
    ax[2].set_title(f"|error| (16-bit levels): max {err.max():.0f}, RMS {rms:.1f}")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return {"frame": frame, "max_error_levels": float(err.max()), "rms_error_levels": rms}
