"""facesynth's benchmarks and studies (not shipped with the package): run from the
repository root as modules, e.g. ``OMP_NUM_THREADS=1 python -m bench.runtime.talking_head``.

Benches, grouped by what they measure: ``train`` (fitting and evaluation), ``export`` (the
ONNX export and its int8 basis), ``runtime`` (rendering speed and the talking head), ``ingest``
(landmarkers and the page's tracker), ``web`` (the live page and the studio), ``mesh`` (3D
transfer, scans and the geometry codec). ``studies`` hold the one-off measurements behind a
decision of the docs (a table, a contact sheet). Each prints one JSON line through
:mod:`bench.harness` (the host's CPU flags and the load average around the run);
:mod:`bench.browser` drives the live page in Chromium for the web benches and the tests.
"""
