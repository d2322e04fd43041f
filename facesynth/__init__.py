"""facesynth: learning-based facial expression synthesis.

The package layout follows the pipeline, and data flows one way through it::

    data -> model -> sadm / eri -> mesh -> codec
                       \\-> runtime (ONNX, torch-free)      eval (metrics, reports)

Conventions used everywhere:

* landmarks are float32 arrays of shape (N, 68, 2) holding (x, y) pixel coordinates
  in 0-based iBUG 300-W order;
* images are uint8 RGB arrays of shape (H, W, 3) at the edges of the library and
  float32 tensors of shape (B, C, H, W) in [0, 1] inside torch.
"""

__version__ = "0.1.0"

from facesynth.errors import FacesynthError  # noqa: E402

__all__ = ["FacesynthError", "__version__"]
