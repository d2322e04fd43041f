"""Preview video and contact sheet of a transferred sequence: the video frame, the posed
mesh rendered over it, and a frontal render of the deformed mesh, side by side."""

from __future__ import annotations

import os

import cv2
import numpy as np

from facesynth.errors import FacesynthError
from facesynth.mesh.render import render_frontal, render_posed
from facesynth.sheet import grid, write_png
from facesynth.videofile import atomic_video


def expression_stats(lm: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame expression measures from landmarks (T, 68, 2), in inter-ocular distances:
    inner-lip gap, mouth width, brow height above the eye-corner line, and the sideways
    offset of the mouth centre from the nose tip along the eye axis."""
    iod = np.linalg.norm(lm[:, 36] - lm[:, 45], axis=1)
    axis = (lm[:, 45] - lm[:, 36]) / iod[:, None]
    up = np.stack([axis[:, 1], -axis[:, 0]], axis=1)  # perpendicular, pointing up in the image
    gap = np.mean([np.linalg.norm(lm[:, a] - lm[:, b], axis=1) for a, b in ((61, 67), (62, 66), (63, 65))], axis=0)
    mid = (lm[:, 36] + lm[:, 45]) / 2
    brow = np.einsum("tkj,tj->tk", lm[:, 17:27] - mid[:, None], up).mean(axis=1)
    mouth_c = lm[:, [48, 54]].mean(axis=1)
    side = np.einsum("tj,tj->t", mouth_c - lm[:, 30], axis)
    return {"mouth_open": gap / iod, "mouth_width": np.linalg.norm(lm[:, 48] - lm[:, 54], axis=1) / iod,
            "brow_height": brow / iod, "mouth_side": side / iod}


def pick_sheet_frames(lm: np.ndarray, neutral: int) -> list[tuple[int, str]]:
    """Rows to show: the neutral frame and the extremes of jaw opening, brow raise (among
    frames with the mouth at most half open), brow lowering, mouth width (narrow and
    wide) and sideways lips (rows of ``lm`` (T, 68, 2), finite)."""
    s = expression_stats(lm)
    closed = s["mouth_open"] <= np.median(s["mouth_open"])  # brow raise without a wide-open jaw
    brow = np.where(closed, s["brow_height"], -np.inf)
    side = np.abs(s["mouth_side"] - s["mouth_side"][neutral])
    picks = [
        (neutral, "neutral ref"), (int(np.argmax(s["mouth_open"])), "jaw open"),
        (int(np.argmax(brow)), "brows raised"), (int(np.argmin(s["brow_height"])), "brows lowered"),
        (int(np.argmin(s["mouth_width"])), "narrow lips"), (int(np.argmax(s["mouth_width"])), "wide lips"),
        (int(np.argmax(side)), "lips sideways"),
    ]
    out, seen = [], set()
    for r, name in picks:
        if r not in seen:
            seen.add(r)
            out.append((r, name))
    return out


def _label(img: np.ndarray, text: str, y: int = 0) -> np.ndarray:
    """White text on a dark box at the top-left (readable on bright frames too)."""
    img = img.copy()
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
    cv2.rectangle(img, (0, y), (tw + 12, y + th + base + 10), (0, 0, 0), -1)
    cv2.putText(img, text, (6, y + th + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return img


ROW_NAMES = ("video + landmarks", "posed mesh over video", "frontal mesh", "frontal: brows and eyes")


def panel(frame: np.ndarray | None, V: np.ndarray, F: np.ndarray, R, t, K, size: tuple[int, int], ref: np.ndarray,
          landmarks: np.ndarray | None = None) -> np.ndarray:
    """One row (H, 3W, 3) uint8: [video frame with landmarks | posed overlay | frontal]."""
    w, h = size
    if frame is None:
        frame = np.full((h, w, 3), 90, np.uint8)
    elif frame.shape[:2] != (h, w):
        raise FacesynthError(f"preview: video frames are {frame.shape[1]}x{frame.shape[0]}, landmarks expect {w}x{h}")
    video = frame.copy()
    if landmarks is not None:
        for x, y in np.round(landmarks).astype(int):
            cv2.circle(video, (int(x), int(y)), 2, (0, 255, 0), -1, cv2.LINE_AA)
    over = render_posed(V, F, R, t, K, w, h, background=frame, alpha=0.75)
    front = cv2.resize(render_frontal(V, F, size=min(w, h), ref=ref), (w, h)) if w != h else \
        render_frontal(V, F, size=w, ref=ref)
    return np.hstack([video, over, front])


class PreviewWriter:
    """Writes rows from :func:`panel` to an .mp4 (OpenCV ``mp4v``), atomically; the video is
    reopened and checked before it is kept (:func:`facesynth.videofile.atomic_video`)."""

    def __init__(self, path: str | os.PathLike, fps: float):
        self.path, self.fps = path, fps
        self._ctx = None
        self._video = None

    def write(self, row: np.ndarray) -> None:
        if self._video is None:
            self._ctx = atomic_video(self.path, self.fps)
            self._video = self._ctx.__enter__()
        try:
            self._video.write(row)
        except BaseException as exc:
            self.close(ok=False, exc=exc)
            raise

    def close(self, ok: bool = True, exc: BaseException | None = None) -> None:
        if self._video is not None:
            ctx, self._video = self._ctx, None
            if ok:
                ctx.__exit__(None, None, None)
            else:
                exc = exc or RuntimeError("aborted")
                ctx.__exit__(type(exc), exc, None)


def contact_sheet(rows: list[np.ndarray], labels: list[str], path: str | os.PathLike, tile: int = 300) -> np.ndarray:
    """Columns of [video; posed overlay; frontal; frontal zoomed on brows and eyes] for
    each picked frame, written as PNG."""
    cols = []
    for row, text in zip(rows, labels, strict=True):
        h, w3 = row.shape[:2]
        w = w3 // 3
        parts = [cv2.resize(row[:, i * w:(i + 1) * w], (tile, tile * h // w), interpolation=cv2.INTER_AREA) for i in range(3)]
        front = row[:, 2 * w:]
        zoom = front[int(0.2 * h):int(0.5 * h), int(0.28 * w):int(0.72 * w)]
        parts.append(cv2.resize(zoom, (tile, tile * zoom.shape[0] // zoom.shape[1]), interpolation=cv2.INTER_CUBIC))
        parts[0] = _label(parts[0], text)
        if not cols:  # name the rows once, in the first column
            parts = [parts[0]] + [_label(p, name) for p, name in zip(parts[1:], ROW_NAMES[1:], strict=True)]
            parts[0] = _label(parts[0], ROW_NAMES[0], y=parts[0].shape[0] - 30)
        cols.append(parts)
    sheet = grid([list(row) for row in zip(*cols, strict=True)])
    write_png(path, sheet)
    return sheet
