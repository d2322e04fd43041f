"""facesynth: learning-based facial expression synthesis.

The package layout follows the pipeline (docs/architecture.md draws it; the imports obey
it, checked by tests/test_layers.py)::

    top      cli (facesynth.cli, every */cli.py)  runs (facesynth train = train.py; configs in conf/)
             eval  onnx (export)  batch  web (the live page's Python side)
    stages   data -> model -> sadm <- regressors      (2D: shape -> appearance)
                          -> eri  <- regressors      (2D: expression ratio images)
             data -> mesh                            (3D wing: pose, Laplacian transfer)
             data -> codec                           (geometry-video wing)
    runtime  torch-free: exported ONNX models, the talking-head app (reads data, ground)
    ground   errors, io, metrics, landmarks, landmark_tables, geometry, imaging, provenance,
             contract, artifact, ops, progress, neutral, faps, retarget, videofile

Conventions used everywhere:

* landmarks are float32 arrays of shape (N, 68, 2) holding (x, y) pixel coordinates
  in 0-based iBUG 300-W order;
* images are uint8 RGB arrays of shape (H, W, 3) at the edges of the library and
  float32 tensors of shape (B, C, H, W) in [0, 1] inside torch.
"""

__version__ = "0.1.0"

from facesynth.errors import FacesynthError  # noqa: E402

__all__ = ["FacesynthError", "__version__"]
