"""Hole filling of open face scans (Xia et al., "Modeling and Compressing 3-D Facial
Expressions Using Geometry Videos", TCSVT 2012, sec. III-B).

Each interior boundary loop is closed by a patch triangulated at the density of the
surrounding mesh (concentric rings advancing from the loop to its centre, each ring
resampled so that its spacing matches the loop's mean edge length, stitched ring to ring by
arc-length parameter, a fan at the centre), whose vertices then solve the bi-Laplace
equation ``L M^-1 L x = 0`` with every original vertex fixed. Only the loop and its first
ring of neighbours enter the rows of the patch vertices, so the patch is a minimal-energy
(thin-plate) surface that meets the mesh with matching position and tangent plane (C1). The
same solve fills per-vertex colours. ``L`` is the cotangent Laplacian of
:mod:`facesynth.mesh.laplacian` and ``M`` the barycentric lumped mass; the solve is redone
on the updated geometry (``iterations``) because the cotangent weights of the initial rings
are those of a planar guess.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from facesynth.errors import FacesynthError
from facesynth.mesh.laplacian import cotangent_laplacian, face_normals, lumped_mass, ordered_boundary_loops


@dataclass
class FilledMesh:
    """Result of :func:`fill_holes`.

    Attributes
    ----------
    vertices : float64 (V + N, 3): the original vertices first, then the N new ones.
    faces : int64 (F + G, 3): the original faces first, then the G patch faces.
    colors : float64 (V + N, C) or None
    n_original : int, V
    loops : list of int64 arrays, the filled loops (ordered as their boundary half-edges).
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None
    n_original: int
    loops: list[np.ndarray]


def _loop_length(V: np.ndarray, loop: np.ndarray) -> float:
    return float(np.linalg.norm(V[np.roll(loop, -1)] - V[loop], axis=1).sum())


def _sample_closed(P: np.ndarray, t: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Points of the closed polyline ``P`` (n, 3) with normalised arc-length ``t`` (n,) at ``params``."""
    te = np.append(t, 1.0)
    Pe = np.vstack([P, P[:1]])
    return np.stack([np.interp(params, te, Pe[:, k]) for k in range(3)], axis=1)


def _stitch(outer: np.ndarray, a: np.ndarray, inner: np.ndarray, b: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles between two closed rings of vertex ids with sorted parameters in [0, 1).

    ``outer`` runs along its boundary half-edges; the strip uses them reversed, so the new
    triangles are oriented consistently with the faces already on the other side.
    """
    m1, m2 = len(outer), len(inner)
    ae, be = np.append(a, 1.0 + a[0]), np.append(b, 1.0 + b[0])
    tris, i, j = [], 0, 0
    while i < m1 or j < m2:
        if j == m2 or (i < m1 and ae[i + 1] <= be[j + 1]):
            tris.append((outer[(i + 1) % m1], outer[i % m1], inner[j % m2]))
            i += 1
        else:
            tris.append((outer[i % m1], inner[j % m2], inner[(j + 1) % m2]))
            j += 1
    return tris


def _patch(V: np.ndarray, loop: np.ndarray, first_id: int) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Initial patch of one loop: new vertex positions (N, 3) and triangles (global ids)."""
    P = V[loop]
    seg = np.linalg.norm(np.roll(P, -1, axis=0) - P, axis=1)
    h = float(seg.mean())
    t = np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / seg.sum()
    c = P.mean(axis=0)
    n_rings = max(1, int(round(float(np.linalg.norm(P - c, axis=1).mean()) / h)))
    new, tris = [], []
    ring, ring_t, nid = loop, t, first_id
    for k in range(1, n_rings):
        s = 1.0 - k / n_rings
        m = int(round(len(loop) * s))
        if m < 6:
            break
        params = np.arange(m) / m
        new.append(c + s * (_sample_closed(P, t, params) - c))
        ids = np.arange(nid, nid + m)
        nid += m
        tris += _stitch(ring, ring_t, ids, params)
        ring, ring_t = ids, params
    new.append(c[None])
    tris += [(ring[(i + 1) % len(ring)], ring[i], nid) for i in range(len(ring))]
    return np.concatenate(new), tris


def _biharmonic(V: np.ndarray, F: np.ndarray, free: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Solve ``(L M^-1 L) x = 0`` on the ``free`` rows with the other rows of ``values`` fixed."""
    L = cotangent_laplacian(V, F)
    Q = (L @ sp.diags(1.0 / np.maximum(lumped_mass(V, F), 1e-300)) @ L).tocsr()
    fixed = np.setdiff1d(np.arange(len(V)), free)
    Qf = Q[free]
    A, B = Qf[:, free].tocsc(), Qf[:, fixed]
    x = spsolve(A, -(B @ values[fixed]))
    out = values.copy()
    out[free] = x.reshape(len(free), -1)
    return out


def fill_holes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None,
               loops: list[np.ndarray] | None = None, keep_open: np.ndarray | None = None,
               iterations: int = 2) -> FilledMesh:
    """Close holes of an open, consistently oriented triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, consistently oriented.
    colors : (V, C) float or None, filled by the same bi-Laplacian solve.
    loops : ordered loops to fill (as from :func:`~facesynth.mesh.laplacian.ordered_boundary_loops`);
        default: every loop but the one with the longest perimeter (the outer rim).
    keep_open : vertex ids; a default loop containing any of them is left open (e.g. the
        eye and mouth loops of a face that should keep them).
    iterations : bi-Laplacian solves, each with the cotangent weights of the previous result.

    Returns
    -------
    FilledMesh (the input unchanged, with no new vertex, when there is nothing to fill).
    """
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise FacesynthError(f"fill_holes: expected vertices (V, 3) and faces (F, 3), got {V.shape}, {F.shape}")
    if colors is not None:
        colors = np.asarray(colors, np.float64).reshape(len(V), -1)
    if loops is None:
        try:
            found = ordered_boundary_loops(F)
        except ValueError as exc:
            raise FacesynthError(f"fill_holes: {exc}") from None
        if len(found) > 1:
            outer = int(np.argmax([_loop_length(V, lp) for lp in found]))
            found = [lp for k, lp in enumerate(found) if k != outer]
        else:
            found = []
        keep = set() if keep_open is None else set(np.asarray(keep_open).tolist())
        loops = [lp for lp in found if not keep.intersection(lp.tolist())]
    loops = [np.asarray(lp, np.int64) for lp in loops]
    new_v, new_f, nid = [], [], len(V)
    for lp in loops:
        if len(lp) < 3:
            raise FacesynthError(f"fill_holes: a loop needs at least 3 vertices, got {len(lp)}")
        pv, pf = _patch(V, lp, nid)
        new_v.append(pv)
        new_f += pf
        nid += len(pv)
    if not loops:
        return FilledMesh(V.copy(), F.copy(), None if colors is None else colors.copy(), len(V), [])
    V2 = np.vstack([V, *new_v])
    F2 = np.vstack([F, np.asarray(new_f, np.int64)])
    free = np.arange(len(V), len(V2))
    for _ in range(max(1, iterations)):
        V2 = _biharmonic(V2, F2, free, V2)
    C2 = None
    if colors is not None:
        C2 = np.vstack([colors, np.zeros((len(free), colors.shape[1]))])
        C2 = _biharmonic(V2, F2, free, C2)
    return FilledMesh(V2, F2, C2, len(V), loops)


def loop_crease_angles(V: np.ndarray, F: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Angle in degrees between the normals of the two triangles on either side of each edge
    of a closed vertex cycle ``loop`` (after filling: the mesh face and the patch face)."""
    F = np.asarray(F, np.int64)
    fn = face_normals(V, F)
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    owner = np.tile(np.arange(len(F)), 3)
    lut = {(int(a), int(b)): int(f) for (a, b), f in zip(he, owner, strict=True)}
    out = []
    for a, b in zip(loop, np.roll(loop, -1), strict=True):
        f1, f2 = lut.get((int(a), int(b))), lut.get((int(b), int(a)))
        if f1 is None or f2 is None:
            raise FacesynthError(f"loop_crease_angles: edge ({a}, {b}) is not interior")
        out.append(np.degrees(np.arccos(np.clip(fn[f1] @ fn[f2], -1.0, 1.0))))
    return np.asarray(out)


def punch_hole(V: np.ndarray, F: np.ndarray, center: int, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove the triangles with a vertex within Euclidean ``radius`` of vertex ``center``.

    Returns the compacted mesh ``(V', F')`` and ``kept`` (V',) int64: the original index of
    each remaining vertex. For tests and benchmarks of :func:`fill_holes`.
    """
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    near = np.linalg.norm(V - V[center], axis=1) < radius
    Fk = F[~near[F].any(axis=1)]
    kept = np.unique(Fk)
    remap = np.full(len(V), -1, np.int64)
    remap[kept] = np.arange(len(kept))
    return V[kept], remap[Fk], kept
