"""Running an exported ERI model (``facesynth export RUN --target ...``) with ONNX Runtime.

The model holds one target face: MPEG-4 FAPs (B, 36) -> the target's face crop, mask and
placement in the target's frame; :meth:`EriRenderer.render_frames` pastes them into the
target's neutral image (or other backgrounds of its size) as ``EriSynthesizer.render``
does. numpy + onnxruntime + OpenCV only (no torch).
"""

from __future__ import annotations

import os

import numpy as np

from facesynth.compositing import blend_rendered
from facesynth.contract import ERI_FORMAT, ERI_FORMAT_V1, ERI_INPUT
from facesynth.errors import FacesynthError
from facesynth.runtime.renderer import Renderer, check_batch


class EriRenderer(Renderer):
    """FAPs -> rendered target faces with an exported ERI model.

    Parameters
    ----------
    model_path : path-like
        An ONNX file written by ``facesynth export RUN --target ...``.
    threads, spin : as :class:`Renderer`.

    Attributes
    ----------
    n_faps : int, FAPs per frame (metadata ``n_faps``; columns in ``metadata["fap_names"]`` order)
    frame_size : (W, H) of the target's frame (placements map into it; metadata ``frame_size``)
    feather : float, compositing edge width (the model's ``eri.feather``)
    """

    format = ERI_FORMAT
    older_formats = (ERI_FORMAT_V1,)  # its frame_size is (H, W)
    input_name = ERI_INPUT
    kind_name = "ERI"

    def __init__(self, model_path: str | os.PathLike, threads: int = 1, spin: bool = False):
        super().__init__(model_path, threads, spin)
        md = self.metadata
        try:
            self.n_faps = int(md["n_faps"])
            size = tuple(int(v) for v in md["frame_size"])
            self.frame_size = size[::-1] if md.get("format") == ERI_FORMAT_V1 else size
        except (KeyError, TypeError, ValueError):
            raise FacesynthError(f"{self.path}: ERI model metadata lacks n_faps / frame_size") from None
        names = md.get("fap_names")
        if not isinstance(names, list) or len(names) != self.n_faps:
            raise FacesynthError(f"{self.path}: metadata fap_names does not list {self.n_faps} FAPs")
        dims = self.session.get_inputs()[0].shape
        if len(dims) != 2 or dims[1] != self.n_faps:
            raise FacesynthError(f"{self.path}: input shape {dims}, expected (batch, {self.n_faps}) (metadata n_faps)")
        self.input_shape = (self.n_faps,)
        self.feather = float(md.get("feather", 3.0))

    def __repr__(self) -> str:
        return (f"EriRenderer({str(self.path)!r}, driver={self.metadata.get('driver')!r}, "
                f"crop={self.crop_size}, frame={self.frame_size}, threads={self.threads})")

    def validate(self, faps) -> np.ndarray:
        """Check (B, n_faps) (or one (n_faps,)) finite real FAPs -> C-contiguous float32 (B, n_faps)."""
        return check_batch(faps, "faps", (self.n_faps,), "MPEG-4 FAP values", "this model's n_faps")

    def render(self, faps, copy: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(B, n_faps) FAPs -> crops float32 (B, 3, Hc, Wc) in [0, 1], masks float32
        (B, 1, Hc, Wc) in {0, 1}, placements float32 (B, 2, 3) crop px -> frame px.
        The arrays are this renderer's buffers unless ``copy`` (see :meth:`Renderer.render`)."""
        return super().render(faps, copy)

    def render_frames(self, faps, background: np.ndarray, feather: float | None = None) -> np.ndarray:
        """Frames uint8 (B, H, W, 3): the rendered faces pasted into ``background`` (uint8
        (H, W, 3) RGB of the target's frame size, normally the target's neutral image, or
        (B, H, W, 3)), as ``EriSynthesizer.render`` (:func:`facesynth.compositing.composite`)."""
        bg = np.asarray(background)
        w, h = self.frame_size
        if bg.dtype != np.uint8 or bg.ndim not in (3, 4) or bg.shape[-3:] != (h, w, 3):
            raise FacesynthError(f"background: expected uint8 ({h}, {w}, 3) (the target's frame size), "
                                 f"got {bg.dtype} {bg.shape}")
        crops, masks, places = self.render(faps)
        if bg.ndim == 4 and len(bg) != len(crops):
            raise FacesynthError(f"background: {len(bg)} frames for a batch of {len(crops)}")
        f = self.feather if feather is None else float(feather)
        return np.stack([
            blend_rendered(crops, masks, places, bg[i] if bg.ndim == 4 else bg, i, feather=f, still=True)
            for i in range(len(crops))
        ])
