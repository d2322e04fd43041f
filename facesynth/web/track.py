"""MediaPipe's crop-and-track face tracking on the converted ONNX models (numpy + OpenCV).

The reference of the page's tracker worker (``web/tracker.js`` does the same steps in the same
order): the face detector finds a face once; then each frame's 468 mesh points are fitted in a
rotated square around the previous frame's points (eye line horizontal, 1.5 x the points' box),
and each eye's 5 iris points in a square of 2.3 x its corner-to-corner distance (the right eye
mirrored, as the iris model expects a left eye). Output: (478, 2) float32 frame pixels, 0-based
pixel centres, ordered as MediaPipe's ``refine_landmarks=True`` (468 mesh, 5 + 5 iris).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

MESH_SIZE, IRIS_SIZE, DET_SIZE = 192, 64, 128
FACE_SCALE, EYE_SCALE = 1.5, 2.3
EYES = ((33, 133), (362, 263))  # (outer, inner) corners of the image-left and image-right eyes
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
    a square of side ``size`` centred on ``center``, its u axis along ``angle`` (radians). As in
    MediaPipe, crop pixel u is sampled at crop coordinate u (not u + 0.5) and a model's point at
    crop coordinate x maps to frame pixel M x: both go through this one matrix."""
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


def _crop(rgb: np.ndarray, m: np.ndarray, out: int, flip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(1, out, out, 3) float32 in [0, 1] and the matrix mapping the model's points to frame pixels;
    ``flip`` mirrors the crop (pixel u <- out - 1 - u; a point x <- out - x)."""
    mirror = lambda w: np.array([[-1, 0, w], [0, 1, 0], [0, 0, 1]], np.float64)  # noqa: E731
    sample = m @ mirror(out - 1) if flip else m
    img = cv2.warpAffine(rgb, sample, (out, out), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT)
    return img.astype(np.float32)[None] / 255.0, (m @ mirror(out) if flip else m)


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
        self.det, self.mesh, self.iris = load("face_detection"), load("face_landmark"), load("iris_landmark")
        self.anchors = _anchors()
        self.prev: np.ndarray | None = None

    def detect(self, rgb: np.ndarray):
        """Face ROI (centre, angle, side) from the detector, or None."""
        h, w = rgb.shape[:2]
        side = max(h, w)
        m = crop_matrix(((w - 1) / 2, (h - 1) / 2), 0.0, side, DET_SIZE)  # letterbox, zeros outside
        x, _ = _crop(rgb, m, DET_SIZE)
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
        m = crop_matrix(*roi, MESH_SIZE)
        x, _ = _crop(rgb, m, MESH_SIZE)
        pts, presence = self.mesh.run(None, {"input": x})
        if 1 / (1 + np.exp(-presence.reshape(()))) < PRESENCE:
            return None
        return _apply(m, pts.reshape(468, 3)[:, :2])

    def iris_points(self, rgb: np.ndarray, mesh: np.ndarray) -> np.ndarray:
        """(10, 2): both eyes' 5 iris points, the two crops in one batch."""
        crops, maps = [], []
        for k, (a, b) in enumerate(EYES):
            c, ang, size = roi_from_points(mesh[[a, b]], 0, 1, EYE_SCALE)
            x, m = _crop(rgb, crop_matrix(c, ang, size, IRIS_SIZE), IRIS_SIZE, flip=k == 1)
            crops.append(x)
            maps.append(m)
        _, iris = self.iris.run(None, {"input": np.concatenate(crops)})
        return np.concatenate([_apply(m, iris[k].reshape(5, 3)[:, :2]) for k, m in enumerate(maps)])

    def track(self, rgb: np.ndarray) -> np.ndarray | None:
        roi = roi_from_points(self.prev, 33, 263, FACE_SCALE) if self.prev is not None else self.detect(rgb)
        if roi is None:
            return None
        mesh = self.mesh_points(rgb, roi)
        self.prev = mesh
        if mesh is None:
            return None
        return np.concatenate([mesh, self.iris_points(rgb, mesh)]).astype(np.float32)
