"""How stair-stepped the talking head's outline is: the full-frame warp's grid against the
exact piecewise affine warp, along the head's outline.

The "affine" :class:`facesynth.runtime.fullframe.FrameWarp` evaluates its piecewise affine
map exactly at the nodes of a grid and interpolates bilinearly between them. Where a
triangle edge with a kink of the map crosses a cell (the jaw: the landmarks follow the
face, the neck points a share of it; the head's ring on the hair's outline), the cell's
bilinear patch departs from the exact map, and an edge of the picture there is drawn as a
staircase of the cells. Two figures, over the silhouette band (:func:`silhouette_band`: the
head region's outline, hair, jaw and neck, not the composited face's inside):

* ``map_px``: how far (px) the warp's map departs from the exact one (the same warp at one
  node per pixel, ``grid_step=1``), 99th percentile and maximum over the band;
* ``staircase``: the gradient energy of the rendered warp's difference from the exact
  warp's rendering over the exact rendering's gradient energy, in the band
  (:func:`edge_staircase`): 0 when they agree; a smooth edge drawn as a staircase adds the
  energy of its steps' risers and treads. It is what the picture shows, the map's error
  weighted by the edges it moves (a wrong map over a plain wall costs nothing).

PSNR against the real frame barely moves with either: the outline is a thin line of pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from facesynth.eval.sharpness import gradient_energy
from facesynth.landmarks import ibug68_view
from facesynth.runtime.fullframe import FrameWarp, face_frame, head_region

BAND = 0.15  # face units (outer-eye-corner distances): the silhouette band's margin


def silhouette_band(face68: np.ndarray, size: tuple[int, int], margin: float = BAND) -> np.ndarray:
    """bool (H, W): where the head's outline lies in a frame of ``size`` (W, H) with the
    (68, 2) landmarks ``face68``: the head region (:func:`head_region`: hair, ears, neck)
    grown by ``margin`` face units, less the landmarks' hull shrunk by as much (the
    composited face's inside); the jaw line and the hair's outline lie in it."""
    w, h = size
    r = max(1, int(round(margin * face_frame(face68)[2])))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    head = cv2.dilate(head_region(face68, size).astype(np.uint8), kernel)
    hull = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(hull, cv2.convexHull(np.round(np.asarray(face68) * 16).astype(np.int32)), 1, cv2.LINE_8, 4)
    return (head > 0) & (cv2.erode(hull, kernel) == 0)


def edge_staircase(rendered: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Gradient energy (:func:`gradient_energy`, Sobel 3x3) of ``rendered - reference`` over
    that of ``reference``, summed over the bool (H, W) ``mask`` (the whole image when None);
    images of one shape, uint8 or float. 0: the same edges; NaN where the reference has no
    gradient in the mask."""
    a, b = np.asarray(rendered, np.float32), np.asarray(reference, np.float32)
    if a.shape != b.shape:
        raise ValueError(f"edge_staircase: images of shapes {a.shape} and {b.shape}")
    region = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    ref = gradient_energy(b)[region].sum()
    return float(gradient_energy(a - b)[region].sum() / ref) if ref > 0 else float("nan")


def exact_warp(fw: FrameWarp) -> FrameWarp:
    """``fw`` at one grid node per pixel: its exact piecewise affine map (the same frame,
    neutral, motion and ring)."""
    return FrameWarp(fw.frame, fw.neutral68, fw.method, fw.motion, fw.ring_scale, grid_step=1)


def outline_figures(fw: FrameWarp, landmarks: np.ndarray, exact: FrameWarp | None = None) -> dict[str, float]:
    """{"map_px_p99", "map_px_max", "staircase"} (module docstring) of ``fw`` driven by the
    (P, 2) avatar ``landmarks``, over their :func:`silhouette_band`; ``exact``:
    :func:`exact_warp` of ``fw`` (made here when None)."""
    exact = exact_warp(fw) if exact is None else exact
    band = silhouette_band(ibug68_view(landmarks), fw.size)
    maps, ref = np.stack(fw.maps(landmarks)), np.stack(exact.maps(landmarks))
    err = np.hypot(*(maps - ref))[band]
    frame = cv2.remap(fw.frame, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    ref_frame = cv2.remap(fw.frame, ref[0], ref[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return {"map_px_p99": float(np.percentile(err, 99)), "map_px_max": float(err.max()),
            "staircase": edge_staircase(frame, ref_frame, band)}


__all__ = ["BAND", "edge_staircase", "exact_warp", "outline_figures", "silhouette_band"]
