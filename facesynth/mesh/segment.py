"""Geodesic face segmentation (Xia et al. 2012, sec. III-C).

The face region is the set of vertices within a geodesic distance ``radius`` of facial
feature points (iBUG-68 landmark vertices) or of the closed contours through them, so that
the same physical region is kept in every frame of a sequence (the paper: 60-65 mm for male,
45-50 mm for female faces). The paper measures from the eye and mouth points with one
radius (``sources="points"``); on expressions that stretch the skin around the mouth by
centimetres (a jaw opening, lips pressed together) the rim under the mouth then moves with
the lips. The default (``sources="anchored"``, :data:`ANCHORED_FEATURES`) measures the upper
face from the skull-rigid eye corners and nose, and gives the mouth and the jaw-rigid chin a
shorter reach, so that the rim lies where the skin follows the bones (figures in
docs/codec.md). Optionally the eyes and mouth are removed (the faces inside the closed eye
contours and inner-lip contour) so that the region has the four boundaries the
parameterisation (:mod:`facesynth.mesh.eip`) expects: outer rim, two eyes, mouth. A feature
that already is a hole (e.g. the ICT face's eye and mouth openings) is left as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from facesynth.errors import FacesynthError
from facesynth.landmarks import INNER_LIPS, JAW, LEFT_EYE, MOUTH, OUTER_LIPS, RIGHT_EYE, RIGID_NOSE_EYES
from facesynth.mesh.laplacian import drop_ears, edges, ordered_boundary_loops
from facesynth.mesh.paths import closed_contour, edge_graph, geodesic_distances

# 0-based iBUG-68 index sets of the features (facesynth.landmarks; the subject's right eye is iBUG 37-42)
EYE_R = np.array(RIGHT_EYE)
EYE_L = np.array(LEFT_EYE)
MOUTH_OUTER = np.array(OUTER_LIPS)
MOUTH_INNER = np.array(INNER_LIPS)
# the contour whose inside is removed for each feature
FEATURE_CONTOURS = {"eye_r": EYE_R, "eye_l": EYE_L, "mouth": MOUTH_INNER}
# sources="anchored": (landmark indices, weight) per feature group; a vertex's distance is the
# least weight x distance to a group, i.e. each group reaches radius / weight. The skull-rigid
# eye corners and nose reach the full radius (forehead, temples, cheeks); the lips, whose
# skin stretches by centimetres under mouth expressions, only half of it, enough to keep the
# mouth inside; the chin (iBUG 8-10), rigid with the jaw, 1 / 2.5 of it, so that the lower rim
# rides on the jaw bone instead of the neck skin that a jaw opening compresses. Measured on
# the ICT blendshapes (docs/codec.md, bench/mesh/scan.py).
ANCHORED_FEATURES = {"eyes_nose": (np.array(RIGID_NOSE_EYES), 1.0), "mouth": (np.array(MOUTH), 2.0),
                     "chin": (np.array(JAW[7:10]), 2.5)}
SOURCES = ("anchored", "points", "contours")


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
                     sources: str | dict = SOURCES[0], method: str = "heat") -> np.ndarray:
    """Distance (V,) of every vertex from the facial features.

    ``sources``: ``anchored`` (the default: eye corners and nose, mouth and chin landmark
    vertices, weighted as in :data:`ANCHORED_FEATURES`), ``points`` (the eye and mouth
    landmark vertices iBUG 37-68, the paper's choice), ``contours`` (every vertex of the
    closed edge paths through the eye and outer-lip landmarks), or a mapping like
    :data:`ANCHORED_FEATURES` (name -> (0-based iBUG indices, weight)). ``metric``:
    ``geodesic`` (see :func:`facesynth.mesh.paths.geodesic_distance`) or ``euclidean``.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    lm = _check_landmarks(landmarks, len(V))
    if metric not in ("geodesic", "euclidean"):
        raise FacesynthError(f"metric: expected 'geodesic' or 'euclidean', got {metric!r}")
    if isinstance(sources, dict) or sources == "anchored":
        table = ANCHORED_FEATURES if sources == "anchored" else sources
        need = np.concatenate([np.asarray(ix, np.int64) for ix, _ in table.values()])
        if (lm[need] < 0).any() or (lm[need] >= len(V)).any():
            raise FacesynthError(f"landmarks: sources needs the landmark vertices {sorted(set((need + 1).tolist()))} "
                                 "(iBUG, 1-based); use sources='points' without them")
        groups = [(lm[np.asarray(ix, np.int64)], float(w)) for ix, w in table.values()]
    elif sources == "points":
        groups = [(lm[np.concatenate([EYE_R, EYE_L, MOUTH_OUTER, MOUTH_INNER])], 1.0)]
    elif sources == "contours":
        g = edge_graph(V, F)
        groups = [(np.concatenate([closed_contour(g, lm[ix]) for ix in (EYE_R, EYE_L, MOUTH_OUTER)]), 1.0)]
    else:
        raise FacesynthError(f"sources: expected one of {SOURCES}, got {sources!r}")
    if metric == "geodesic":
        dist = geodesic_distances(V, F, [src for src, _ in groups], method)
    else:
        from scipy.spatial import cKDTree

        dist = [cKDTree(V[np.unique(src)]).query(V)[0] for src, _ in groups]
    return np.min([w * d for d, (_, w) in zip(dist, groups, strict=True)], axis=0)


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


def _close_islands(V: np.ndarray, F: np.ndarray, Fk: np.ndarray) -> np.ndarray:
    """``Fk`` (rows of ``F``) plus every patch of ``F`` left out of it but enclosed by it (a
    spot beyond the radius inside the region, e.g. skin stretched between two features that
    neither reaches): the region's holes are then only the mesh's own openings."""
    _, inv = np.unique(np.concatenate([F, Fk]), axis=0, return_inverse=True)
    inv = inv.ravel()
    taken = np.zeros(inv.max() + 1, bool)
    taken[inv[len(F):]] = True
    out = ~taken[inv[:len(F)]]
    loops = ordered_boundary_loops(Fk)
    if len(loops) < 2 or not out.any():
        return Fk
    rim = loops[int(np.argmax([np.linalg.norm(V[np.roll(lp, -1)] - V[lp], axis=1).sum() for lp in loops]))]
    Fo = F[out]
    lab = _components(Fo)
    outside = np.unique(lab[np.isin(Fo, rim).any(axis=1)])
    return np.concatenate([Fk, Fo[~np.isin(lab, outside)]])


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
                 sources: str | dict = SOURCES[0], remove_features: bool | str = True, method: str = "heat",
                 colors: np.ndarray | None = None) -> FaceRegion:
    """Cut the face region out of a mesh (see the module docstring). Spots beyond the radius
    that the region encloses are kept: its only holes are the mesh's own openings and, with
    ``remove_features``, the features.

    Parameters
    ----------
    vertices : (V, 3) float; faces : (F, 3) int, consistently oriented.
    landmarks : (68,) int, iBUG-68 landmark vertices (eyes and mouth required; the default
        ``sources`` also needs the nose and chin ones).
    radius : float, in mesh units (ICT: cm); the reach of the skull-rigid features.
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
    Fk = _close_islands(V, F, drop_ears(Fk[lab == np.bincount(hit).argmax()]))
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
