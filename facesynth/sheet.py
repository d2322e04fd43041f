"""Contact sheets: a grid of image tiles (uint8 RGB), with an optional header naming the
columns, written as PNG. ``app --contact-sheet``, ``transfer-expression --sheet`` and
``transfer3d --contact-sheet`` each choose their tiles; the grid and the file are made here."""

from __future__ import annotations

import os

import cv2
import numpy as np

from facesynth.errors import FacesynthError
from facesynth.io import write_bytes

HEADER_PX = 28  # height of the header row that names the columns


def grid(rows: list[list[np.ndarray]], columns: tuple[str, ...] = ()) -> np.ndarray:
    """The tiles ``rows`` (each row's tiles of one height, each row of one width) as one
    uint8 RGB image; ``columns``: labels drawn on a white header above the first row's tiles."""
    sheet = np.concatenate([np.concatenate(row, 1) for row in rows], 0)
    if not columns:
        return sheet
    head = np.full((HEADER_PX, sheet.shape[1], 3), 255, np.uint8)
    x = 0
    for tile, label in zip(rows[0], columns, strict=False):
        cv2.putText(head, label, (x + 8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        x += tile.shape[1]
    return np.concatenate([head, sheet], 0)


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """uint8 RGB ``rgb`` as a PNG file at ``path``, written atomically."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover
        raise FacesynthError(f"{path}: PNG encoding failed")
    write_bytes(path, buf.tobytes())
