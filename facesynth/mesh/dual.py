"""Differential coordinates that follow the surface, for the iterative Laplacian editors.

Each class gives a fixed sparse operator ``op`` (M, N) on the primal vertices, the rest
coordinates ``delta0 = op V0`` (M, 3), and ``delta(V)``: the rest coordinates re-expressed
on the current mesh V (rotation-invariant encoding, Au et al. 2006).

- :class:`PrimalCoordinates`: cotangent Laplacian; each delta is stored in the local frame
  (tangent towards the farthest neighbour, bitangent, area-weighted vertex normal) of its
  vertex, so its length is kept and its normal part follows the current normal.
- :class:`DualCoordinates`: dual mesh (vertices = triangle centroids ``q = D V``). A dual
  vertex with three neighbours q_a, q_b, q_c (an interior triangle) is encoded as in Au,
  Tai, Liu & Fu, "Dual Laplacian Editing for Meshes" (TVCG 2006): its projection on the
  plane of its neighbours, as barycentric weights w, and its signed height h along that
  plane's normal. The in-plane part is linear, so it goes into the operator,
  ``(q - sum_j w_j q_j)``, and only ``delta = h n(q_a, q_b, q_c)`` changes with the
  surface. Dual vertices on the mesh boundary (fewer than three neighbours) use the
  umbrella Laplacian with a face-normal frame.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from facesynth.mesh.laplacian import (
    cotangent_laplacian,
    edges,
    face_adjacency,
    face_centroid_operator,
    face_normals,
    vertex_normals,
)


def frames(normals: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Orthonormal frames (K, 3, 3), rows (tangent, bitangent, normal); the tangent is
    ``ref`` (K, 3) projected on the plane normal to ``normals`` (K, 3)."""
    t = ref - np.einsum("ij,ij->i", ref, normals)[:, None] * normals
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    return np.stack([t, np.cross(normals, t), normals], axis=1)


def farthest_neighbour(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """For each vertex, the 1-ring neighbour at the longest edge (N,): the best-conditioned
    tangent reference (a very short edge at a fold would make the frame jitter)."""
    E = edges(F)
    length = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    i, j, ll = np.concatenate([E[:, 0], E[:, 1]]), np.concatenate([E[:, 1], E[:, 0]]), np.concatenate([length, length])
    order = np.lexsort((-ll, i))
    i, j = i[order], j[order]
    first = np.r_[True, i[1:] != i[:-1]]
    out = np.zeros(len(V), np.int64)
    out[i[first]] = j[first]
    return out


class PrimalCoordinates:
    """Cotangent Laplacian coordinates in per-vertex local frames (normal: area-weighted
    vertex normal; tangent: towards the farthest 1-ring neighbour)."""

    def __init__(self, V0: np.ndarray, F: np.ndarray):
        self.F = F
        self.op = cotangent_laplacian(V0, F)
        self.ref_nb = farthest_neighbour(V0, F)
        self.delta0 = np.asarray(self.op @ V0)
        self.coef0 = np.einsum("kij,kj->ki", self._frames(V0), self.delta0)

    def _frames(self, V):
        return frames(vertex_normals(V, self.F), V[self.ref_nb] - V)

    def delta(self, V: np.ndarray) -> np.ndarray:
        return np.einsum("kij,ki->kj", self._frames(V), self.coef0)


class DualCoordinates:
    """Dual-mesh coordinates (Au et al. 2006), see the module docstring."""

    def __init__(self, V0: np.ndarray, F: np.ndarray):
        self.F = F
        m, n = len(F), len(V0)
        self.D = face_centroid_operator(F, n)
        A = face_adjacency(F)
        deg = np.asarray(A.sum(axis=1)).ravel().astype(int)
        Q0 = np.asarray(self.D @ V0)
        inner = np.flatnonzero(deg == 3)
        nb = np.vstack([A.indices[A.indptr[i]:A.indptr[i + 1]] for i in inner]) if len(inner) else np.zeros((0, 3), int)
        qa, qb, qc = Q0[nb[:, 0]], Q0[nb[:, 1]], Q0[nb[:, 2]]
        nrm = np.cross(qb - qa, qc - qa)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        # orient each neighbour-plane normal like its own face's normal
        self.sign = np.where(np.einsum("ij,ij->i", nrm, face_normals(V0, F)[inner]) < 0, -1.0, 1.0)
        nrm *= self.sign[:, None]
        q = Q0[inner]
        self.h = np.einsum("ij,ij->i", q - qa, nrm)
        p = q - self.h[:, None] * nrm
        # barycentric weights of p in (qa, qb, qc), least squares on the two edge vectors
        E = np.stack([qb - qa, qc - qa], axis=2)  # (K, 3, 2)
        uv = np.linalg.solve(np.einsum("kij,kil->kjl", E, E), np.einsum("kij,ki->kj", E, p - qa)[..., None])[..., 0]
        w = np.column_stack([1 - uv.sum(axis=1), uv])
        rows = np.concatenate([inner, np.repeat(inner, 3)])
        cols = np.concatenate([inner, nb.ravel()])
        vals = np.concatenate([np.ones(len(inner)), -w.ravel()])
        self.inner, self.nb = inner, nb
        # boundary dual vertices: umbrella over the available neighbours
        outer = np.flatnonzero(deg < 3)
        Ao = A[outer].tocoo()
        rows = np.concatenate([rows, outer, outer[Ao.row]])
        cols = np.concatenate([cols, outer, Ao.col])
        vals = np.concatenate([vals, np.ones(len(outer)), -1.0 / np.maximum(deg[outer][Ao.row], 1)])
        Lq = sp.csr_matrix((vals, (rows, cols)), shape=(m, m))
        self.op = (Lq @ self.D).tocsr()
        self.outer = outer
        self.delta0 = np.asarray(self.op @ V0)
        self.coef0 = np.einsum("kij,kj->ki", self._outer_frames(V0, Q0), self.delta0[outer])

    def _outer_frames(self, V, Q):
        fo = self.F[self.outer]
        return frames(face_normals(V, fo), V[fo[:, 0]] - Q[self.outer])

    def delta(self, V: np.ndarray) -> np.ndarray:
        Q = np.asarray(self.D @ V)
        out = np.empty((len(self.F), 3))
        qa, qb, qc = Q[self.nb[:, 0]], Q[self.nb[:, 1]], Q[self.nb[:, 2]]
        nrm = np.cross(qb - qa, qc - qa) * self.sign[:, None]
        out[self.inner] = self.h[:, None] * nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        out[self.outer] = np.einsum("kij,ki->kj", self._outer_frames(V, Q), self.coef0)
        return out
