"""Geodesic face segmentation (Xia et al. 2012, sec. III-C).

The face region is the set of vertices within a geodesic distance ``radius`` of the eye and
mouth feature points (iBUG-68 landmark vertices) or of the closed contours through them.
Skin stretches little under expression, so geodesic distances are nearly invariant and the
same physical region is kept in every frame of a sequence (the paper: 60-65 mm for male,
45-50 mm for female faces); a Euclidean ball is not (an open jaw moves the chin away from
the mouth points in space, not along the skin). Optionally the eyes and mouth are removed
(the faces inside the closed eye contours and inner-lip contour) so that the region has the
four boundaries the parameterisation (:mod:`facesynth.mesh.eip`) expects: outer rim, two
eyes, mouth. A feature that already is a hole (e.g. the ICT face's eye and mouth openings)
is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from facesynth.errors import FacesynthError
from facesynth.landmarks import INNER_LIPS, LEFT_EYE, OUTER_LIPS, RIGHT_EYE
from facesynth.mesh.laplacian import drop_ears, edges, ordered_boundary_loops
from facesynth.mesh.paths import closed_contour, edge_graph, geodesic_distance

# 0-based iBUG-68 index sets of the features (facesynth.landmarks; the subject's right eye is iBUG 37-42)
EYE_R = np.array(RIGHT_EYE)
EYE_L = np.array(LEFT_EYE)
MOUTH_OUTER = np.array(OUTER_LIPS)
MOUTH_INNER = np.array(INNER_LIPS)
# the contour whose inside is removed for each feature
FEATURE_CONTOURS = {"eye_r": EYE_R, "eye_l": EYE_L, "mouth": MOUTH_INNER}


@dataclass
class FaceRegion:
    """A segmented face.

    Attributes
    ----------
    vertices : float64 (n, 3)
    faces : int64 (m, 3)
    kept : int64 (n,), the input vertex index of each vertex.
    loops : dict ``outer``, ``eye_r``, ``eye_l``, ``mouth`` -> ordered loop (local ids); the
        features that have no loop are absent.
    extra_loops : list of other boundary loops (holes not filled).
    colors : (n, C) or None
    """

    vertices: np.ndarray
    faces: np.ndarray
    kept: np.ndarray
    loops: dict[str, np.ndarray]
    extra_loops: list[np.ndarray] = field(default_factory=list)
    colors: np.ndarray | None = None


def _check_landmarks(landmarks, n_vertices: int) -> np.ndarray:
    lm = np.asarray(landmarks, np.int64).ravel()
    if lm.shape != (68,):
        raise FacesynthError(f"landmarks: expected 68 vertex indices (iBUG order), got {lm.shape}")
    need = np.concatenate([EYE_R, EYE_L, MOUTH_OUTER, MOUTH_INNER])
    if (lm[need] < 0).any() or (lm[need] >= n_vertices).any():
        raise FacesynthError(f"landmarks: eye and mouth landmarks (iBUG 37-68) must be vertices 0..{n_vertices - 1}")
    return lm


def feature_distance(V: np.ndarray, F: np.ndarray, landmarks, metric: str = "geodesic",
                     sources: str = "points", method: str = "heat") -> np.ndarray:
    """Distance (V,) of every vertex from the eye and mouth features.

    ``sources``: ``points`` (the landmark vertices iBUG 37-68) or ``contours`` (every vertex
    of the closed edge paths through the eye and outer-lip landmarks). ``metric``:
    ``geodesic`` (see :func:`facesynth.mesh.paths.geodesic_distance`) or ``euclidean``.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    lm = _check_landmarks(landmarks, len(V))
    if sources == "points":
        src = lm[np.concatenate([EYE_R, EYE_L, MOUTH_OUTER, MOUTH_INNER])]
    elif sources == "contours":
        g = edge_graph(V, F)
        src = np.concatenate([closed_contour(g, lm[ix]) for ix in (EYE_R, EYE_L, MOUTH_OUTER)])
    else:
        raise FacesynthError(f"sources: expected 'points' or 'contours', got {sources!r}")
    if metric == "geodesic":
        return geodesic_distance(V, F, src, method)
    if metric == "euclidean":
        from scipy.spatial import cKDTree

        return cKDTree(V[np.unique(src)]).query(V)[0]
    raise FacesynthError(f"metric: expected 'geodesic' or 'euclidean', got {metric!r}")


def _components(F: np.ndarray, cut: set[tuple[int, int]] | None = None) -> np.ndarray:
    """Connected component label of each face across shared edges not in ``cut`` (sorted pairs)."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(F)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, owner = e[order], owner[order]
    same = (e[1:] == e[:-1]).all(axis=1)
    if cut:
        blocked = np.array([tuple(x) in cut for x in e[1:].tolist()], bool)
        same &= ~blocked
    a, b = owner[:-1][same], owner[1:][same]
    A = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(len(F), len(F)))
    return connected_components(A, directed=False)[1]


def _remove_inside(V: np.ndarray, F: np.ndarray, contour: np.ndarray, what: str,
                   opening: np.ndarray | None = None) -> np.ndarray:
    """Faces kept after removing those enclosed by the closed vertex cycle ``contour``: the
    component (across edges not on the contour) touching the feature's existing ``opening``
    loop if there is one, else the one nearest the contour's centroid."""
    cut = {tuple(sorted((int(a), int(b)))) for a, b in zip(contour, np.roll(contour, -1), strict=True)}
    lab = _components(F, cut)
    if opening is not None:
        inside = np.isin(lab, np.unique(lab[np.isin(F, opening).any(axis=1)]))
    else:
        centre = V[contour].mean(axis=0)
        inside = lab == lab[int(np.argmin(np.linalg.norm(V[F].mean(axis=1) - centre, axis=1)))]
    if inside.sum() * 2 > len(F) or not inside.any():
        raise FacesynthError(f"{what}: its landmark contour does not enclose a small patch of the mesh "
                             "(closed mouth or a contour running off the surface?)")
    return F[~inside]


def _compact(V: np.ndarray, F: np.ndarray, kept: np.ndarray):
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F], kept[used], used


def label_loops(V: np.ndarray, F: np.ndarray, landmarks: np.ndarray) -> tuple[dict[str, np.ndarray], list]:
    """Name the boundary loops: ``outer`` (longest perimeter) and, for each feature, the
    loop whose centroid is nearest its landmark centroid (within the contour's radius).
    ``landmarks`` are (68,) local vertex ids, -1 where absent."""
    loops = ordered_boundary_loops(F)
    if not loops:
        raise FacesynthError("segmentation: the region has no boundary (a closed surface)")
    per = [float(np.linalg.norm(V[np.roll(lp, -1)] - V[lp], axis=1).sum()) for lp in loops]
    out = {"outer": loops[int(np.argmax(per))]}
    rest = [lp for k, lp in enumerate(loops) if k != int(np.argmax(per))]
    for name, ix in FEATURE_CONTOURS.items():
        ids = landmarks[ix]
        if (ids < 0).any() or not rest:
            continue
        c = V[ids].mean(axis=0)
        reach = np.linalg.norm(V[ids] - c, axis=1).max()
        dist = [np.linalg.norm(V[lp].mean(axis=0) - c) for lp in rest]
        k = int(np.argmin(dist))
        if dist[k] <= reach:
            out[name] = rest.pop(k)
    return out, rest


def segment_face(vertices: np.ndarray, faces: np.ndarray, landmarks, radius: float, metric: str = "geodesic",
                 sources: str = "points", remove_features: bool | str = True, method: str = "heat",
                 colors: np.ndarray | None = None) -> FaceRegion:
    """Cut the face region out of a mesh (see the module docstring).

    Parameters
    ----------
    vertices : (V, 3) float; faces : (F, 3) int, consistently oriented.
    landmarks : (68,) int, iBUG-68 landmark vertices (eyes and mouth required).
    radius : float, in mesh units (ICT: cm).
    metric, sources, method : see :func:`feature_distance`.
    remove_features : cut out the eyes and mouth that are not holes already (True), or cut
        every feature at its landmark contour, widening an existing opening to it ("always":
        the openings then follow the landmarks, e.g. the inner-lip line instead of a mouth
        bag behind the lips).
    colors : (V, C) or None, carried along.
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    lm = _check_landmarks(landmarks, len(V))
    if not radius > 0:
        raise FacesynthError(f"radius: expected > 0, got {radius}")
    d = feature_distance(V, F, lm, metric, sources, method)
    Fk = F[(d[F] <= radius).all(axis=1)]
    if len(Fk) == 0:
        raise FacesynthError(f"radius {radius}: no triangle lies within it")
    lab = _components(Fk)
    feat = lm[np.concatenate([EYE_R, EYE_L, MOUTH_INNER])]
    hit = lab[np.isin(Fk, feat).any(axis=1)]
    if len(hit) == 0:
        raise FacesynthError(f"radius {radius}: the features' triangles are not in the region")
    Fk = drop_ears(Fk[lab == np.bincount(hit).argmax()])
    Vc, Fc, kept, _ = _compact(V, Fk, np.arange(len(V)))
    local = np.full(len(V), -1, np.int64)
    local[kept] = np.arange(len(kept))
    lmc = local[lm]
    if remove_features not in (False, True, "always"):
        raise FacesynthError(f"remove_features: expected False, True or 'always', got {remove_features!r}")
    if remove_features:
        loops, _ = label_loops(Vc, Fc, lmc)
        for name, ix in FEATURE_CONTOURS.items():
            if name in loops and remove_features != "always":
                continue
            if (lmc[ix] < 0).any():
                raise FacesynthError(f"{name}: its landmarks fall outside radius {radius}")
            contour = closed_contour(edge_graph(Vc, Fc), lmc[ix])
            try:
                Fc = _remove_inside(Vc, Fc, contour, name, loops.get(name))
            except FacesynthError:
                if name not in loops:
                    raise  # else keep the existing opening (the contour crossed it or collapsed)
        Vc, Fc, kept2, used = _compact(Vc, Fc, kept)
        loc2 = np.full(len(kept), -1, np.int64)
        loc2[used] = np.arange(len(used))
        lmc = np.where(lmc >= 0, loc2[np.maximum(lmc, 0)], -1)
        kept = kept2
    loops, rest = label_loops(Vc, Fc, lmc)
    if len(edges(Fc)) == 0:
        raise FacesynthError("segmentation: empty region")
    col = None if colors is None else np.asarray(colors, np.float64).reshape(len(V), -1)[kept]
    return FaceRegion(Vc, Fc, kept, loops, rest, col)
