"""iBUG ``.pts`` landmark files (version 1).

The format is 1-based: pixel centre of the top-left pixel is (1, 1). facesynth is
0-based, so reading subtracts 1 and writing adds 1 -- visibly, here and nowhere else.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.io import write_text
from facesynth.landmarks import N_LANDMARKS


def read_pts(path: str | os.PathLike, n_points: int | None = N_LANDMARKS) -> np.ndarray:
    """Read one ``.pts`` file.

    Returns
    -------
    np.ndarray
        float32, shape (n_points, 2): 0-based (x, y) pixel coordinates.
    """
    path = Path(path)
    try:
        lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    except OSError as exc:
        raise FacesynthError(f"{path}: cannot read .pts file ({exc.strerror})") from None
    try:
        header = {k.strip(): v.strip() for k, v in (ln.split(":", 1) for ln in lines[: lines.index("{")])}
        n = int(header["n_points"])
        body = lines[lines.index("{") + 1 : lines.index("}")]
        pts = np.array([[float(t) for t in ln.split()] for ln in body], dtype=np.float64)
    except (ValueError, KeyError) as exc:
        raise FacesynthError(f"{path}: not a valid .pts file (expected 'n_points: N' and a '{{ x y ... }}' block)") from exc
    if pts.shape != (n, 2):
        raise FacesynthError(f"{path}: header says {n} points but the block holds {pts.shape[0]} rows of (x y)")
    if n_points is not None and n != n_points:
        markup = " (iBUG 68-point markup)" if n_points == N_LANDMARKS else ""
        raise FacesynthError(f"{path}: has {n} landmarks, expected {n_points}{markup}")
    return (pts - 1.0).astype(np.float32)


def write_pts(path: str | os.PathLike, landmarks: np.ndarray) -> None:
    """Write (n, 2) 0-based (x, y) landmarks as a 1-based ``.pts`` file (atomically)."""
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 2 or lm.shape[1] != 2:
        raise FacesynthError(f"{path}: landmarks must have shape (n, 2), got {lm.shape}")
    if not np.isfinite(lm).all():
        raise FacesynthError(f"{path}: landmarks contain NaN/inf; .pts cannot mark missing points")
    body = "\n".join(f"{x + 1:.3f} {y + 1:.3f}" for x, y in lm)
    write_text(path, f"version: 1\nn_points: {len(lm)}\n{{\n{body}\n}}\n")
