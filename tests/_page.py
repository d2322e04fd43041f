"""One skip guard for the tests that build or open the live page: they need the tracker's
converter (``tflite``, MediaPipe's models), onnxruntime-web (``facesynth web setup``) and, to
open it, Playwright with a system Chromium. Called at a module's top or inside a fixture."""

from __future__ import annotations

import pytest


def require_page(open_in_browser: bool = False) -> None:
    """Skip (the module, or the test calling it) without what a built page needs; with
    ``open_in_browser`` also without Playwright or Chromium."""
    if open_in_browser:
        pytest.importorskip("playwright")
    pytest.importorskip("tflite")
    pytest.importorskip("mediapipe")
    if open_in_browser:
        from bench import browser

        if browser.chromium_path() is None:
            pytest.skip("chromium is absent (apt-get install chromium)", allow_module_level=True)
    from facesynth.web import site

    try:
        site.ort_dist()
    except Exception as exc:  # FacesynthError naming the missing file
        pytest.skip(str(exc), allow_module_level=True)
