"""Running an exported synthesis model with ONNX Runtime (numpy + onnxruntime, no torch).

``Renderer(model_path).render(landmarks)`` keeps one inference session, binds
preallocated output buffers per batch size (``run_with_iobinding``, no per-call output
allocation) and fixes the thread settings once. Inputs are validated (shape, dtype, NaN)
and the model's metadata (format, landmark scheme) is checked on loading.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from facesynth import __version__
from facesynth.compositing import STILL_FEATHER, blend_rendered
from facesynth.contract import FORMAT_HINTS, OUTPUT_NAMES, SYNTHESIS_FORMAT, SYNTHESIS_INPUT
from facesynth.errors import FacesynthError
from facesynth.landmarks import SCHEMES, scheme_for_points
from facesynth.runtime.checks import (
    as_array,
    check_coordinate_range,
    check_face_extent,
    check_metadata_size,
    check_outputs,
)
from facesynth.runtime.cpu import check_int8_basis


def read_metadata(model_path: str | os.PathLike) -> dict:
    """Metadata properties of an exported model, JSON values decoded (the model is loaded
    without its graph optimisations: a look at its metadata, not a session to run)."""
    sess = _session(Path(model_path), 1, False, optimize=False)
    return _decode(sess.get_modelmeta().custom_metadata_map)


def _decode(props: dict) -> dict:
    out = {}
    for k, v in props.items():
        try:
            out[k] = json.loads(v)
        except (json.JSONDecodeError, TypeError):
            out[k] = v
    return out


def _session(path: Path, threads: int, spin: bool, optimize: bool = True) -> ort.InferenceSession:
    if not path.is_file():
        raise FacesynthError(f"{path}: model file not found")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimize else \
        ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    so.log_severity_level = 3
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several types for unreadable models
        raise FacesynthError(f"{path}: not a loadable ONNX model ({str(exc).splitlines()[0][:200]})") from None


def check_batch(values, field: str, item: tuple[int, ...], unit: str, layout: str, nan_hint: str = "") -> np.ndarray:
    """Validate a batch of model inputs: real dtype, shape (B, *item) (one (*item) is
    promoted to a batch of 1), all finite. Returns C-contiguous float32 (B, *item); raises
    FacesynthError naming ``field``, what was expected and the offending batch rows."""
    x = as_array(values, field)
    if x.dtype.kind not in "fiu":
        raise FacesynthError(f"{field}: expected a float array of {unit}, got dtype {x.dtype}")
    if x.ndim == len(item):
        x = x[None]
    if x.ndim != len(item) + 1 or x.shape[1:] != tuple(item) or x.shape[0] < 1:
        raise FacesynthError(f"{field}: expected shape (B, {', '.join(map(str, item))}) ({layout}), got {tuple(np.shape(values))}")
    x = np.ascontiguousarray(x, np.float32)
    if not np.isfinite(x).all():
        bad = np.flatnonzero(~np.isfinite(x.reshape(len(x), -1)).all(axis=1))
        raise FacesynthError(f"{field}: NaN or infinite values in batch rows {bad[:10].tolist()}{nan_hint}")
    return x


class Renderer:
    """Landmarks -> rendered face crops with an exported facesynth model.

    Parameters
    ----------
    model_path : path-like
        An ONNX file written by ``facesynth export``.
    threads : int
        Intra-op threads of the session (1 = lowest latency per core).
    spin : bool
        Let idle worker threads spin (lower latency with ``threads > 1``, burns CPU).

    Attributes
    ----------
    metadata : dict
        The model's metadata (facesynth version, regressor, reference size, ...).
    crop_size : (H, W)
    channels : int
    """

    format = SYNTHESIS_FORMAT
    older_formats: tuple[str, ...] = ()  # earlier versions of the format this class still reads
    input_name = SYNTHESIS_INPUT
    kind_name = "synthesis"

    def __init__(self, model_path: str | os.PathLike, threads: int = 1, spin: bool = False):
        if int(threads) < 1:
            raise FacesynthError(f"threads must be >= 1, got {threads}")
        self.path = Path(model_path)
        self.session = _session(self.path, threads, spin)
        self.threads = int(threads)
        self.metadata = _decode(self.session.get_modelmeta().custom_metadata_map)
        where = str(self.path)
        fmt = self.metadata.get("format")
        if fmt != self.format and fmt not in self.older_formats:
            hint = f" ({FORMAT_HINTS[fmt]})" if fmt in FORMAT_HINTS else ""
            raise FacesynthError(f"{where}: not a facesynth {self.kind_name} model (format {fmt!r}, expected {self.format!r}){hint}")
        name = self.metadata.get("landmark_scheme")
        if name not in SCHEMES:
            raise FacesynthError(f"{where}: landmark scheme {name!r}; this runtime knows {', '.join(sorted(SCHEMES))}")
        self.scheme = SCHEMES[name]
        check_int8_basis(self.metadata, where)  # older int8 files saturate on x86 without VNNI
        if self.metadata.get("n_landmarks", self.scheme.n_points) != self.scheme.n_points:
            raise FacesynthError(f"{where}: metadata 'n_landmarks' is {self.metadata.get('n_landmarks')!r}, but scheme "
                                 f"{name!r} has {self.scheme.n_points} points")
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs != [self.input_name] or tuple(outputs) != OUTPUT_NAMES:
            raise FacesynthError(f"{where}: inputs {inputs} / outputs {outputs}, expected [{self.input_name}] / {list(OUTPUT_NAMES)}")
        self.input_shape: tuple[int, ...] = (self.scheme.n_points, 2)
        dims = self.session.get_inputs()[0].shape
        if self.input_name == SYNTHESIS_INPUT and (len(dims) != 3 or dims[1] != self.scheme.n_points):
            raise FacesynthError(f"{where}: input shape {dims}, expected (B, {self.scheme.n_points}, 2) for {name}")
        channels = self.metadata.get("channels", 3)
        if channels not in (1, 3):
            raise FacesynthError(f"{where}: metadata 'channels' is {channels!r}, expected 1 or 3")
        self.channels = int(channels)
        key = "canvas_size" if "canvas_size" in self.metadata else "reference_size"
        self.crop_size = check_metadata_size(self.metadata.get(key), where, key)
        self._bindings: dict[int, tuple] = {}

    def __repr__(self) -> str:
        return (f"Renderer({str(self.path)!r}, regressor={self.metadata.get('regressor')!r}, "
                f"crop={self.crop_size}, threads={self.threads})")

    # ------------------------------------------------------------ validation
    def validate(self, landmarks) -> np.ndarray:
        """Check (B, P, 2) (or one (P, 2)) finite real landmarks of the model's scheme (P its
        point count) -> C-contiguous float32 (B, P, 2). Another scheme's points are an error
        that names both schemes."""
        landmarks = as_array(landmarks, "landmarks")  # a ragged list fails here, clearly
        shape = landmarks.shape
        other = scheme_for_points(shape[-2]) if len(shape) >= 2 and shape[-1] == 2 else None
        if other is not None and other is not self.scheme:
            raise FacesynthError(f"landmarks: this model takes {self.scheme.name} landmarks ({self.scheme.n_points} points), "
                                 f"got {other.name} ones {tuple(shape)} (the driver and the model must share a scheme"
                                 + (f"; map them with get_scheme({other.name!r}).to_ibug68(...)" if self.scheme.name == "ibug68" else "")
                                 + ")")
        n = self.scheme.n_points
        x = check_batch(landmarks, "landmarks", (n, 2), "(x, y) pixels", f"{self.scheme.name} points, x y",
                        " (drop frames without a face)")
        check_coordinate_range(x)
        check_face_extent(x)
        return x

    # -------------------------------------------------------------- running
    def _binding(self, batch: int):
        got = self._bindings.get(batch)
        if got is None:
            h, w = self.crop_size
            bufs = (
                np.empty((batch, self.channels, h, w), np.float32),
                np.empty((batch, 1, h, w), np.float32),
                np.empty((batch, 2, 3), np.float32),
            )
            inp = np.empty((batch, *self.input_shape), np.float32)
            io = self.session.io_binding()
            io.bind_cpu_input(self.input_name, inp)
            for name, buf in zip(OUTPUT_NAMES, bufs, strict=True):
                io.bind_ortvalue_output(name, ort.OrtValue.ortvalue_from_numpy(buf))
            got = (io, inp, bufs)
            self._bindings[batch] = got
        return got

    def render(self, landmarks, copy: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render faces for a batch of landmark sets.

        Parameters
        ----------
        landmarks : (B, P, 2) or (P, 2) array, frame pixels (x, y), in the model's scheme
            (``self.scheme``: P = 68 for ibug68, 478 for mediapipe478)
        copy : bool
            Return copies; by default the returned arrays are this renderer's output
            buffers, overwritten by the next call with the same batch size.

        Returns
        -------
        crops : float32 (B, C, H, W) in [0, 1], zeros outside the face
        masks : float32 (B, 1, H, W) in {0, 1}
        placements : float32 (B, 2, 3) crop pixels -> frame pixels
        """
        x = self.validate(landmarks)
        io, inp, bufs = self._binding(len(x))
        np.copyto(inp, x)
        self.session.run_with_iobinding(io)
        check_outputs(str(self.path), crops=bufs[0], masks=bufs[1], placements=bufs[2])
        return tuple(b.copy() for b in bufs) if copy else bufs

    def render_frame(self, landmarks, background: np.ndarray, feather: float = STILL_FEATHER) -> np.ndarray:
        """One face composited into a frame.

        landmarks : (P, 2) frame pixels; background : uint8 (H, W, 3) RGB.
        Returns uint8 (H, W, 3) (see :func:`facesynth.compositing.composite`).
        """
        bg = np.asarray(background)
        if bg.dtype != np.uint8 or bg.ndim != 3 or bg.shape[2] != 3:
            raise FacesynthError(f"background: expected uint8 (H, W, 3), got {bg.dtype} {bg.shape}")
        x = self.validate(landmarks)
        if len(x) != 1:
            raise FacesynthError(f"render_frame: one face at a time, got a batch of {len(x)}")
        return blend_rendered(*self.render(x), bg, feather=feather, still=True)


__all__ = ["Renderer", "read_metadata", "__version__"]
