"""MediaPipe's crop-and-track face tracking on the converted ONNX models (numpy + OpenCV).

The reference of the page's tracker worker (``page/tracker.js`` does the same steps in the same
order): the face detector finds a face once; then each frame's points come from the attention
mesh in a rotated square around the previous frame's points (eye line horizontal, 1.5 x the
points' box). The mesh is the one behind ``refine_landmarks=True``, refined inside the converted
graph, so the output is MediaPipe's: (478, 2) float32 frame pixels, 0-based pixel centres
(468 mesh, 5 + 5 iris).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

MESH_SIZE, DET_SIZE = 192, 128
FACE_SCALE = 1.5
PRESENCE = 0.5


def _anchors() -> np.ndarray:
    """BlazeFace short-range anchors (896, 2): centres in [0, 1], strides 8 (2 each) and 16 (6 each)."""
    out = []
    for stride, n in ((8, 2), (16, 6)):
        g = DET_SIZE // stride
        ys, xs = np.mgrid[0:g, 0:g]
        c = np.stack([(xs + 0.5) / g, (ys + 0.5) / g], -1).reshape(-1, 1, 2)
        out.append(np.repeat(c, n, axis=1).reshape(-1, 2))
    return np.concatenate(out).astype(np.float32)


def crop_matrix(center, angle: float, size: float, out: int) -> np.ndarray:
    """(2, 3) affine map from crop coordinates (u, v) of an ``out`` x ``out`` crop to frame pixels:
    a square of side ``size`` centred on ``center``, its u axis along ``angle`` (radians). A
    model's point at crop coordinate x maps to frame pixel M x; crop pixel u is sampled at
    M u shifted as ``_crop`` says."""
    c, s = np.cos(angle), np.sin(angle)
    k = size / out
    lin = np.array([[c * k, -s * k], [s * k, c * k]])
    t = np.asarray(center, np.float64) - lin @ np.array([out / 2, out / 2])
    return np.hstack([lin, t[:, None]])


def roi_from_points(pts: np.ndarray, a: int, b: int, scale: float):
    """Centre, angle and side of MediaPipe's square ROI: the points' box centre, the angle of
    the line from point ``a`` to ``b``, ``scale`` x the box's longer side."""
    lo, hi = pts.min(0), pts.max(0)
    d = pts[b] - pts[a]
    return (lo + hi) / 2, float(np.arctan2(d[1], d[0])), float((hi - lo).max() * scale)


def _crop(rgb: np.ndarray, m: np.ndarray, out: int) -> np.ndarray:
    """(1, out, out, 3) float32 in [0, 1]: ``rgb`` sampled bilinearly at M(u, v) + (0.5, 0.5),
    zeros outside. MediaPipe maps its crop onto the image in continuous coordinates (a pixel's
    left edge at 0) and samples there as if they were pixel centres: half a pixel right and down
    of M(u, v) in ours (without the shift the points sit half a pixel off, docs/web.md)."""
    sample = m + np.array([[0, 0, 0.5], [0, 0, 0.5]])
    img = cv2.warpAffine(rgb, sample, (out, out), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT)
    return img.astype(np.float32)[None] / 255.0


def _apply(m: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return uv @ m[:, :2].T + m[:, 2]


class OnnxFaceTracker:
    """Track one face through frames: ``track(rgb) -> (478, 2) float32 or None``."""

    def __init__(self, model_dir: str | Path):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        load = lambda n: ort.InferenceSession(str(Path(model_dir) / f"{n}.onnx"), opts,  # noqa: E731
                                              providers=["CPUExecutionProvider"])
        self.det, self.mesh = load("face_detection"), load("face_landmark")
        self.anchors = _anchors()
        self.prev: np.ndarray | None = None

    def detect(self, rgb: np.ndarray):
        """Face ROI (centre, angle, side) from the detector, or None."""
        h, w = rgb.shape[:2]
        side = max(h, w)
        m = crop_matrix(((w - 1) / 2, (h - 1) / 2), 0.0, side, DET_SIZE)  # letterbox, zeros outside
        x = _crop(rgb, m, DET_SIZE)
        raw, logit = self.det.run(None, {"input": x * 2 - 1})
        k = int(np.argmax(logit[0, :, 0]))
        if 1 / (1 + np.exp(-np.clip(logit[0, k, 0], -100, 100))) < 0.5:
            return None
        r = raw[0, k] / DET_SIZE
        ctr = self.anchors[k] + r[0:2]
        box = r[2:4]
        eyes = self.anchors[k] + r[4:8].reshape(2, 2)  # subject's right eye, left eye
        to_px = lambda p: _apply(m, p * DET_SIZE)  # noqa: E731
        c, e = to_px(ctr), to_px(eyes)
        d = e[1] - e[0]
        return c, float(np.arctan2(d[1], d[0])), float(box.max() * side * FACE_SCALE)

    def mesh_points(self, rgb: np.ndarray, roi) -> np.ndarray | None:
        """(478, 2) float32 frame pixels from the mesh cropped at ``roi``, or None (no face)."""
        m = crop_matrix(*roi, MESH_SIZE)
        pts, presence = self.mesh.run(None, {"input": _crop(rgb, m, MESH_SIZE)})
        if 1 / (1 + np.exp(-presence.reshape(()))) < PRESENCE:
            return None
        return _apply(m, pts[0]).astype(np.float32)

    def track(self, rgb: np.ndarray) -> np.ndarray | None:
        roi = roi_from_points(self.prev, 33, 263, FACE_SCALE) if self.prev is not None else self.detect(rgb)
        if roi is None:
            return None
        self.prev = self.mesh_points(rgb, roi)
        return self.prev
