"""Discrete Laplacians of triangle meshes (scipy.sparse) and mesh-quality measures.

The cotangent Laplacian (Pinkall & Polthier 1993; Meyer et al. 2003) used here is the
un-normalised one, ``L = D - W`` with ``W_ij = (cot alpha_ij + cot beta_ij) / 2`` (the
angles opposite edge ij in its one or two triangles) and ``D = diag(sum_j W_ij)``.
``delta = L V`` are the Laplacian (differential) coordinates: for an interior vertex
``delta_i = sum_j W_ij (v_i - v_j)``, which is ``A_i H_i n_i`` (area times mean
curvature along the normal), zero on a flat patch. L is symmetric positive semi-definite.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _cotangents(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """cot of the angle at each corner, (F, 3): column k is the angle at vertex F[:, k]."""
    cots = np.empty(F.shape, float)
    for k in range(3):
        a = V[F[:, (k + 1) % 3]] - V[F[:, k]]
        b = V[F[:, (k + 2) % 3]] - V[F[:, k]]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        cots[:, k] = np.einsum("ij,ij->i", a, b) / np.maximum(cross, 1e-300)
    return cots


def cotangent_weights(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """Symmetric weight matrix W (V, V) with ``W_ij = (cot alpha_ij + cot beta_ij) / 2``."""
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64)
    cots = _cotangents(V, F)
    rows, cols, vals = [], [], []
    for k in range(3):  # the angle at corner k is opposite edge (k+1, k+2)
        i, j = F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        rows += [i, j]
        cols += [j, i]
        vals += [0.5 * cots[:, k]] * 2
    n = len(V)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def cotangent_laplacian(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """Cotangent Laplacian ``L = D - W``, (V, V) CSR; see the module docstring."""
    W = cotangent_weights(V, F)
    return (sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W).tocsr()


def uniform_laplacian(adjacency: sp.spmatrix) -> sp.csr_matrix:
    """Umbrella Laplacian ``I - D^-1 A`` of a graph with 0/1 adjacency A (n, n)."""
    A = sp.csr_matrix(adjacency, dtype=float)
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (sp.eye(A.shape[0]) - sp.diags(1.0 / np.maximum(deg, 1)) @ A).tocsr()


def face_normals(V: np.ndarray, F: np.ndarray, unit: bool = True) -> np.ndarray:
    """Face normals (F, 3) (right-hand rule on the vertex order); area-weighted if not unit."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300) if unit else n


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals (V, 3)."""
    fn = face_normals(V, F, unit=False)
    out = np.zeros_like(V, dtype=float)
    for k in range(3):
        np.add.at(out, F[:, k], fn)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def boundary_vertices(F: np.ndarray, n_vertices: int) -> np.ndarray:
    """Boolean (V,): vertices on an edge used by exactly one triangle."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    out = np.zeros(n_vertices, bool)
    out[uniq[count == 1].ravel()] = True
    return out


def boundary_loops(F: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Vertex sets (sorted int arrays) of the boundary loops (connected components of the
    boundary edges), largest first."""
    from scipy.sparse.csgraph import connected_components

    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    be = uniq[count == 1]
    if len(be) == 0:
        return []
    A = sp.coo_matrix((np.ones(len(be)), (be[:, 0], be[:, 1])), shape=(n_vertices, n_vertices))
    _, lab = connected_components(A, directed=False)
    bv = np.unique(be)
    loops = [bv[lab[bv] == k] for k in np.unique(lab[bv])]
    return sorted(loops, key=len, reverse=True)


def face_adjacency(F: np.ndarray) -> sp.csr_matrix:
    """Dual graph (F, F): 1 where two triangles share an edge (valence <= 3)."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(F)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, owner = e[order], owner[order]
    same = (e[1:] == e[:-1]).all(axis=1)
    a, b = owner[:-1][same], owner[1:][same]
    m = len(F)
    return sp.csr_matrix((np.ones(2 * len(a)), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(m, m))


def face_centroid_operator(F: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """D (F, V) with ``D V`` = triangle centroids (the dual mesh's vertices)."""
    m = len(F)
    return sp.csr_matrix((np.full(3 * m, 1.0 / 3.0), (np.repeat(np.arange(m), 3), F.ravel())), shape=(m, n_vertices))


def edges(F: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2)."""
    return np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)


def distortion(V0: np.ndarray, V1: np.ndarray, F: np.ndarray) -> dict[str, float]:
    """Edge-length and triangle-area distortion of V1 against the rest mesh V0.

    Returns the mean and 95th percentile of ``|l1 / l0 - 1|`` over edges and of
    ``|A1 / A0 - 1|`` over triangles, plus the fraction of flipped triangles (normal
    turned by more than 90 degrees).
    """
    E = edges(F)
    l0 = np.linalg.norm(V0[E[:, 0]] - V0[E[:, 1]], axis=1)
    l1 = np.linalg.norm(V1[E[:, 0]] - V1[E[:, 1]], axis=1)
    n0, n1 = face_normals(V0, F, unit=False), face_normals(V1, F, unit=False)
    a0, a1 = np.linalg.norm(n0, axis=1), np.linalg.norm(n1, axis=1)
    de, da = np.abs(l1 / l0 - 1), np.abs(a1 / a0 - 1)
    return {
        "edge_mean": float(de.mean()), "edge_p95": float(np.percentile(de, 95)),
        "area_mean": float(da.mean()), "area_p95": float(np.percentile(da, 95)),
        "flipped_fraction": float((np.einsum("ij,ij->i", n0, n1) < 0).mean()),
    }


def lumped_mass(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Barycentric lumped mass (V,): a third of the area of each triangle at each of its corners."""
    a = 0.5 * np.linalg.norm(face_normals(V, F, unit=False), axis=1)
    return np.bincount(np.asarray(F).ravel(), np.repeat(a, 3), minlength=len(V))


def ordered_boundary_loops(F: np.ndarray) -> list[np.ndarray]:
    """Boundary loops as ordered vertex cycles (int64 arrays), longest first.

    Each loop follows the direction of its boundary half-edges in ``F`` (edge ``a -> b`` of
    the one triangle using it), so with consistently oriented faces the surface lies on the
    left of every loop: the outer rim runs counter-clockwise seen from the normals' side and
    a hole clockwise. Raises ValueError on a boundary vertex with more than one outgoing
    boundary edge (a pinched, non-manifold boundary).
    """
    F = np.asarray(F, np.int64)
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.sort(he, axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    bnd = he[count[inv.ravel()] == 1]
    if len(np.unique(bnd[:, 0])) != len(bnd):
        raise ValueError("pinched boundary: a vertex starts two boundary edges")
    nxt = dict(zip(bnd[:, 0].tolist(), bnd[:, 1].tolist(), strict=True))
    loops, seen = [], set()
    for start in bnd[:, 0].tolist():
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.asarray(loop, np.int64))
    return sorted(loops, key=len, reverse=True)


def drop_ears(F: np.ndarray) -> np.ndarray:
    """Remove triangles with two or three boundary edges (the teeth of a cut along a distance
    level or a staircase) until none is left."""
    F = np.asarray(F, np.int64)
    while True:
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
        nb = (cnt[inv.ravel()] == 1).reshape(3, -1).sum(0)
        if not (nb >= 2).any():
            return F
        F = F[nb < 2]
