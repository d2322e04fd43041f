"""ONNX export (torch side): the synthesis graph (:mod:`facesynth.onnx.synthesis`), the
ERI graph (:mod:`facesynth.onnx.eri`), what both share (:mod:`facesynth.onnx.common`: the
closed-form similarity alignment, the writer, the parity check), the graph passes
(:mod:`facesynth.onnx.passes`) and the ``facesynth export`` command (:mod:`facesynth.onnx.cli`).

The files' contract (format strings, names, metadata keys) is :mod:`facesynth.contract`,
which the torch-free runtime reads too.
"""
