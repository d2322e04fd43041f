"""The report's "face moving" strip: consecutive held-out frames, real above, rendered below.

A run of ``n`` test frames ``stride`` frames apart from the middle of the test segment, the
face synthesized from each frame's landmarks (sigma 0) and pasted into its real frame with
:func:`facesynth.compositing.blend_face` (as the app shows it), every tile cut from the
same frame box (the union of the frames' landmark boxes plus a margin) so that the head's
motion shows, and scaled to ``height`` pixels.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from facesynth.compositing import blend_rendered
from facesynth.errors import FacesynthError
from facesynth.io import write_bytes


def strip_rows(n_test: int, n: int = 8, stride: int = 3) -> np.ndarray:
    """Positions (into the test rows) of ``n`` frames ``stride`` apart, centred in the test
    segment (fewer, with a smaller stride, when it is short)."""
    stride = max(1, min(stride, (n_test - 1) // max(n - 1, 1)))
    span = stride * (min(n, n_test) - 1)
    start = max(0, (n_test - 1 - span) // 2)
    return start + stride * np.arange(min(n, n_test))


def strip_tiles(syn, seq, rows: np.ndarray, height: int = 128, margin: float = 0.15) -> list[dict]:
    """[{"frame": row, "real": uint8 (h, w, 3), "synth": uint8 (h, w, 3)}] for sequence rows ``rows``.

    ``syn``: the run's :class:`~facesynth.sadm.synthesis.Synthesizer` (its input scheme's landmarks)."""
    lm = np.ascontiguousarray(seq.landmarks[rows], np.float32)
    n_model = syn.model_points
    pts = lm[:, :n_model].reshape(-1, 2)
    lo, hi = pts.min(0), pts.max(0)
    pad = margin * float((hi - lo).max())
    with torch.no_grad():
        crops, masks, places = (t.numpy() for t in syn(torch.from_numpy(lm)))
    tiles = []
    for j, frame in enumerate(seq.iter_frames(rows)):
        shown = blend_rendered(crops, masks, places, frame, j)
        tiles.append(box_tile(int(rows[j]), frame, shown, lo - pad, hi + pad, height))
    return tiles


def box_tile(row: int, real: np.ndarray, synth: np.ndarray, lo, hi, height: int) -> dict:
    """A strip tile: the box ``lo``..``hi`` (x, y frame pixels, clipped to the frame) of the
    real frame and the rendered one, both uint8 (H, W, 3), scaled to ``height`` pixels high."""
    h, w = real.shape[:2]
    x0, y0 = np.maximum(np.floor(lo).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(hi).astype(int), [w, h])
    size = (max(1, round((x1 - x0) * height / (y1 - y0))), height)
    return {"frame": row, "real": cv2.resize(real[y0:y1, x0:x1], size, interpolation=cv2.INTER_AREA),
            "synth": cv2.resize(synth[y0:y1, x0:x1], size, interpolation=cv2.INTER_AREA)}


def write_strip(tiles: list[dict], path) -> None:
    """:func:`strip_image` as a PNG at ``path`` (written atomically)."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(strip_image(tiles), cv2.COLOR_RGB2BGR))
    if not ok:
        raise FacesynthError(f"{path}: could not encode the strip as PNG")
    write_bytes(path, data.tobytes())


def strip_image(tiles: list[dict], gap: int = 2) -> np.ndarray:
    """uint8 RGB: the real tiles in the top row, the rendered ones below, ``gap`` px apart (white)."""
    h, w = tiles[0]["real"].shape[:2]
    out = np.full((2 * h + gap, len(tiles) * (w + gap) - gap, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        out[:h, i * (w + gap) : i * (w + gap) + w] = t["real"]
        out[h + gap :, i * (w + gap) : i * (w + gap) + w] = t["synth"]
    return out
