"""Raw face scan -> face region with per-vertex parametric coordinates: hole filling
(:mod:`~facesynth.mesh.holes`), geodesic segmentation (:mod:`~facesynth.mesh.segment`) and
the expression-invariant parameterisation (:mod:`~facesynth.mesh.eip`), or the plain
harmonic map to a disk for comparison. Each frame of a sequence is processed on its own
(scans of one sequence need not share a topology); the codec's geometry-image builder
consumes the coordinates as it does UVs (``facesynth codec scan``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.mesh.eip import Domain, harmonic_disk, parameterise
from facesynth.mesh.holes import fill_holes
from facesynth.mesh.laplacian import ordered_boundary_loops
from facesynth.mesh.segment import FEATURE_CONTOURS, SOURCES, segment_face

# The paper's radius for male faces, 60-65 mm, in the ICT face's units (cm).
DEFAULT_RADIUS = 6.0
METHODS = ("eip", "hm")


@dataclass
class ScanFrame:
    """One processed frame.

    Attributes
    ----------
    vertices : float64 (n, 3); faces : int64 (m, 3)
    source : int64 (n,), input vertex of each vertex, -1 for a hole-filling vertex.
    uv : float64 (n, 2) in [0, 1]^2 (v up).
    loops : the region's named loops (local ids).
    filled : number of holes filled; flipped, untangled : see :class:`~facesynth.mesh.eip.EIPResult`.
    colors : (n, C) or None
    """

    vertices: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    uv: np.ndarray
    loops: dict[str, np.ndarray]
    filled: int
    flipped: int
    untangled: int
    colors: np.ndarray | None = None


def _feature_loop_vertices(V: np.ndarray, F: np.ndarray, lm: np.ndarray) -> np.ndarray:
    """Vertices of the boundary loops that are the eye and mouth openings (kept open)."""
    out = []
    try:
        loops = ordered_boundary_loops(F)
    except ValueError as exc:
        raise FacesynthError(f"scan: {exc}") from None
    for ix in FEATURE_CONTOURS.values():
        c = V[lm[ix]].mean(axis=0)
        reach = np.linalg.norm(V[lm[ix]] - c, axis=1).max()
        for lp in loops:
            if np.linalg.norm(V[lp].mean(axis=0) - c) <= reach:
                out.append(lp)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def process_scan(vertices: np.ndarray, faces: np.ndarray, landmarks, radius: float = DEFAULT_RADIUS,
                 method: str = "eip", fill: bool = True, colors: np.ndarray | None = None,
                 domain: Domain | None = None, metric: str = "geodesic", features: bool | str = "always",
                 sources: str = SOURCES[0]) -> ScanFrame:
    """Fill, segment and parameterise one scan.

    Parameters
    ----------
    vertices : (V, 3); faces : (F, 3), consistently oriented with normals towards the viewer.
    landmarks : (68,) int, iBUG-68 landmark vertices (eyes and mouth needed, and with the
        default ``sources`` the nose and chin 8-10; nose 28, 31, 34 and upper lip 52 steer the
        EIP's cuts when present, -1 where absent).
    radius : segmentation radius in mesh units (:data:`DEFAULT_RADIUS`, for cm).
    method : ``eip`` (expression-invariant) or ``hm`` (harmonic map to the disk).
    fill : fill the holes that are not the rim, the eyes or the mouth first.
    sources : segmentation sources (:func:`~facesynth.mesh.segment.feature_distance`).
    features : ``remove_features`` of :func:`~facesynth.mesh.segment.segment_face`; the
        default cuts every opening at its landmark contour, so that the mouth is the inner-lip
        line in every frame.
    """
    if method not in METHODS:
        raise FacesynthError(f"method: expected one of {METHODS}, got {method!r}")
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    lm = np.asarray(landmarks, np.int64).ravel()
    if lm.shape != (68,) or lm.max() >= len(V):
        raise FacesynthError(f"landmarks: expected 68 vertex indices below {len(V)}, got shape {lm.shape}")
    n_filled = 0
    if fill:
        fm = fill_holes(V, F, colors=colors, keep_open=_feature_loop_vertices(V, F, lm))
        V, F, colors, n_filled = fm.vertices, fm.faces, fm.colors, len(fm.loops)
    region = segment_face(V, F, lm, radius, metric=metric, sources=sources, colors=colors, remove_features=features)
    if region.extra_loops:
        raise FacesynthError(f"scan: {len(region.extra_loops)} holes left inside the face region (fill them)")
    local = np.full(len(V), -1, np.int64)
    local[region.kept] = np.arange(len(region.kept))
    lml = np.where(lm >= 0, local[np.maximum(lm, 0)], -1)
    source = np.where(region.kept < len(vertices), region.kept, -1)
    if method == "eip":
        res = parameterise(region.vertices, region.faces, region.loops, lml, domain)
        uv, flipped, moved = res.uv, res.flipped, res.untangled
    else:
        from facesynth.mesh.eip import signed_areas

        outer = region.loops["outer"]
        start = None
        if lml[8] >= 0:
            start = int(outer[np.argmin(np.linalg.norm(region.vertices[outer] - region.vertices[lml[8]], axis=1))])
        uv = harmonic_disk(region.vertices, region.faces, outer, start)
        flipped, moved = int((signed_areas(uv, region.faces) <= 0).sum()), 0
    return ScanFrame(region.vertices, region.faces, source, uv, region.loops, n_filled, flipped, moved, region.colors)


def _near_rim(fr: ScanFrame, rings: int) -> np.ndarray:
    import scipy.sparse as sp

    n = len(fr.vertices)
    E = np.concatenate([fr.faces[:, [0, 1]], fr.faces[:, [1, 2]], fr.faces[:, [2, 0]]])
    A = sp.csr_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n))
    A = A + A.T
    near = np.zeros(n, bool)
    near[fr.loops["outer"]] = True
    for _ in range(rings - 1):
        near |= (A @ near.astype(float)) > 0
    return near if rings > 0 else np.zeros(n, bool)


def uv_drift(frames: list[ScanFrame], size: int, reference: int = 0, skip_rings: int = 0) -> dict[str, float]:
    """How far (in pixels of a ``size``-pixel geometry image) the same input vertex moves
    between the reference frame's parameterisation and each other frame's, over the vertices
    kept in both (and, with ``skip_rings``, farther than that many rings from the reference
    frame's rim): mean, 95th percentile and max over all (frame, vertex) pairs."""
    ref = frames[reference]
    near = _near_rim(ref, skip_rings)
    pos = {int(s): k for k, s in enumerate(ref.source) if s >= 0 and not near[k]}
    d = []
    for t, fr in enumerate(frames):
        if t == reference:
            continue
        src = fr.source
        ok = np.array([s >= 0 and int(s) in pos for s in src])
        k_ref = np.array([pos[int(s)] for s in src[ok]], np.int64)
        d.append(np.linalg.norm(fr.uv[ok] - ref.uv[k_ref], axis=1) * size)
    if not d:
        return {"mean_px": 0.0, "p95_px": 0.0, "max_px": 0.0}
    d = np.concatenate(d)
    return {"mean_px": float(d.mean()), "p95_px": float(np.percentile(d, 95)), "max_px": float(d.max())}
