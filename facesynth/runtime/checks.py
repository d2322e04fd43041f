"""Input and output checks of the runtime (torch-free): landmark coordinates within a stated
range and near the frame, frame sizes within a stated limit, finite model outputs.

Limits: coordinates within +-:data:`MAX_COORD` pixels (float32 still resolves 1/128 px
there, so the similarity alignment inside the model stays exact to well under a pixel);
output frames at most :data:`MAX_FRAME_SIDE` pixels a side; every face's points within one
frame size of the frame (a face may be partly outside the picture, not elsewhere).
"""

from __future__ import annotations

import numpy as np

from facesynth.errors import FacesynthError

MAX_COORD = float(2**16)
MAX_FRAME_SIDE = 8192


def _rows(mask: np.ndarray) -> str:
    rows = np.flatnonzero(mask)
    return f"{rows[:10].tolist()}{' ...' if len(rows) > 10 else ''} ({len(rows)} of {len(mask)})"


def check_coordinate_range(landmarks: np.ndarray, field: str = "landmarks") -> None:
    """FacesynthError when a finite coordinate of (B, P, 2) lies beyond +-MAX_COORD pixels."""
    x = np.asarray(landmarks)
    with np.errstate(invalid="ignore"):
        far = (np.abs(x) > MAX_COORD).any(axis=tuple(range(1, x.ndim)))
    if far.any():
        raise FacesynthError(f"{field}: coordinates beyond +-{MAX_COORD:g} px in rows {_rows(far)}; "
                             "landmarks are frame pixels (x, y)")


def check_face_extent(landmarks: np.ndarray, field: str = "landmarks") -> None:
    """FacesynthError naming the rows of finite (B, P, 2) whose points all lie within 1 px (a
    collapsed face: the models' similarity alignment divides by its size)."""
    x = np.asarray(landmarks)
    extent = (x.max(1) - x.min(1)).max(1)  # (B,) larger side of each face's bounding box
    if (extent < 1.0).any():
        bad = np.flatnonzero(extent < 1.0)
        raise FacesynthError(f"{field}: degenerate faces (all {x.shape[1]} points within 1 px) in batch rows "
                             f"{bad[:10].tolist()}")


def check_frame_size(size: tuple[int, int], field: str) -> tuple[int, int]:
    """(W, H) within [16, MAX_FRAME_SIDE], else FacesynthError naming ``field``."""
    w, h = size
    if not (16 <= w <= MAX_FRAME_SIDE and 16 <= h <= MAX_FRAME_SIDE):
        raise FacesynthError(f"{field}: a {w}x{h} frame is beyond the {MAX_FRAME_SIDE} px limit per side "
                             "(landmarks in other units, or outlier frames? pass --size WxH or fix the landmarks)")
    return w, h


def check_outputs(where: str, **outputs: np.ndarray) -> None:
    """FacesynthError when a model output holds NaN or infinite values (a corrupt model)."""
    for name, value in outputs.items():
        if not np.isfinite(value).all():
            raise FacesynthError(f"{where}: the model's output {name!r} is not finite (corrupt or tampered model?)")


def check_metadata_size(value, where: str, field: str) -> tuple[int, int]:
    """A model's (H, W) metadata entry: two ints in [1, MAX_FRAME_SIDE], else FacesynthError."""
    try:
        h, w = (int(v) for v in value)
    except (TypeError, ValueError):
        raise FacesynthError(f"{where}: metadata {field!r} is {value!r}, expected [H, W]") from None
    if not (1 <= h <= MAX_FRAME_SIDE and 1 <= w <= MAX_FRAME_SIDE):
        raise FacesynthError(f"{where}: metadata {field!r} is {value!r}, expected sides in [1, {MAX_FRAME_SIDE}]")
    return h, w


def as_array(values, field: str) -> np.ndarray:
    """``np.asarray(values)``; FacesynthError for ragged or non-numeric nested lists."""
    try:
        return np.asarray(values)
    except (ValueError, TypeError) as exc:
        raise FacesynthError(f"{field}: not a rectangular array ({str(exc).splitlines()[0][:120]})") from None
