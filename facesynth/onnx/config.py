"""The settings of an export, with their defaults (one place: ``facesynth export``'s options
and the Hydra front end ``export/export.py`` both read them). Torch-free, so that
``facesynth export --help`` stays fast."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from omegaconf import MISSING

from facesynth.contract import OPSET

DEFAULT_COMPONENTS = 40  # appearance components kept at export (docs/runtime.md has the measurements)
BASIS_KINDS = ("int8", "float32")
DEFAULT_BASIS = "int8"  # the exported appearance basis (facesynth.sadm.quantize; docs/runtime.md)


@dataclass
class ExportConfig:
    """run: training run directory; out: output .onnx (written atomically); opset; check:
    compare ONNX Runtime against torch once after writing; components: appearance
    components kept (largest predicted variance over the training landmarks; 0 = all, no
    compression); predicted_variance: instead, keep the fewest components holding this
    fraction of the predicted variance; basis: int8 (integer matmul, PSNR against float32
    recorded) or float32.

    ERI (exported instead when ``target`` is set): target: a neutral face image or an
    ingest folder; target_landmarks: its landmarks (.npy / .pts; default detected);
    target_frame: the row used as neutral (default automatic); variant: SVR variant
    (default the model's driver); raw_ratios: no edge confidence / brightening cap."""

    run: str = MISSING
    out: str = "model.onnx"
    opset: int = OPSET
    check: bool = True
    components: Optional[int] = DEFAULT_COMPONENTS
    predicted_variance: Optional[float] = None
    basis: str = DEFAULT_BASIS
    target: Optional[str] = None
    target_landmarks: Optional[str] = None
    target_frame: Optional[int] = None
    variant: Optional[str] = None
    raw_ratios: bool = False
