"""Laplacian mesh deformation with handle constraints (Sorkine et al., "Laplacian Surface
Editing", SGP 2004), the iterative Laplacian update and dual Laplacian editing of Au,
Tai, Liu and Fu ("Dual Laplacian Editing for Meshes", IEEE TVCG 12(3), 2006).

Plain solve: ``min_V' ||Lop V' - delta||^2`` with the handle vertices fixed on their
targets (hard: the handle columns are eliminated) or pulled by a weight w (soft:
``+ w^2 ||V'_h - targets||^2``). The normal equations are factorised once per mesh and
handle set (``scipy.sparse.linalg.splu``); a frame is then one sparse product and one
triangular solve for all three coordinates.

Iterative (Au et al.): the rest Laplacian coordinates do not rotate with the surface,
so large edits shear. The coordinates are encoded rotation-invariantly
(:mod:`facesynth.mesh.dual`): after each solve they are rebuilt on the current mesh
(original length, along the current normal) and the system is solved again, until the
relative change ``||V_k+1 - V_k|| / ||V_k+1 - V_rest||`` falls below ``tol``.

Dual: the same on the dual mesh (vertices = triangle centroids ``D V``, valence 3), with
the primal vertices as unknowns so that the handles stay primal vertices:
``min ||L_d D V' - delta_d(V)||^2``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from facesynth.errors import FacesynthError
from facesynth.mesh.dual import DualCoordinates, PrimalCoordinates
from facesynth.mesh.laplacian import cotangent_laplacian

DEFORM_METHODS = ("plain", "iterative", "dual")


class LaplacianSystem:
    """Factorised least-squares system ``min ||A_op V - delta||^2`` s.t. handles.

    Parameters
    ----------
    op : sparse (M, N) differential operator acting on the N vertices.
    handles : int (H,) vertex indices, unique.
    constraints : ``"hard"`` (handles exactly on targets) or ``"soft"``.
    weight : soft-constraint weight w (relative to the operator's scale).
    """

    def __init__(self, op: sp.spmatrix, handles: np.ndarray, constraints: str = "hard", weight: float = 1.0):
        op = sp.csc_matrix(op)
        n = op.shape[1]
        handles = np.asarray(handles, np.int64)
        if len(np.unique(handles)) != len(handles):
            raise FacesynthError("laplacian: handle vertices must be unique")
        if len(handles) == 0 or handles.min() < 0 or handles.max() >= n:
            raise FacesynthError(f"laplacian: handle indices must lie in 0..{n - 1}")
        if constraints not in ("hard", "soft"):
            raise FacesynthError(f"laplacian: constraints must be 'hard' or 'soft', got {constraints!r}")
        self.n, self.handles, self.constraints = n, handles, constraints
        if constraints == "hard":
            free = np.setdiff1d(np.arange(n), handles)
            A = op[:, free]
            self.free = free
            self.At = A.T.tocsr()
            self.AtB = (self.At @ op[:, handles]).tocsr()
            N = (self.At @ A).tocsc()
        else:
            S = sp.csr_matrix((np.ones(len(handles)), (np.arange(len(handles)), handles)), shape=(len(handles), n))
            self.At = op.T.tocsr()
            self.wSt = (weight**2 * S.T).tocsr()
            N = (self.At @ op + self.wSt @ S).tocsc()
        try:
            self.lu = spla.splu(N, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as exc:  # singular: a connected component without any handle
            raise FacesynthError(f"laplacian: system is singular ({exc}); every connected part of the mesh needs a handle") from None

    def solve(self, delta: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Vertices (N, 3) for Laplacian coordinates ``delta`` (M, 3) and handle targets (H, 3)."""
        targets = np.asarray(targets, float)
        if self.constraints == "hard":
            V = np.empty((self.n, 3))
            V[self.free] = self.lu.solve(np.asarray(self.At @ delta - self.AtB @ targets))
            V[self.handles] = targets
            return V
        return self.lu.solve(np.asarray(self.At @ delta + self.wSt @ targets))


@dataclass
class DeformInfo:
    """What one deformation did: iterations (1 for plain), converged, last relative change."""

    iterations: int = 1
    converged: bool = True
    rel_change: list[float] = field(default_factory=list)


class LaplacianDeformer:
    """Deform a rest mesh so that handle vertices reach targets.

    Parameters
    ----------
    V0 : (N, 3) rest vertices; F : (F, 3) triangles.
    handles : (H,) vertex indices.
    method : ``plain`` (cotangent Laplacian, one solve), ``iterative`` (Au et al. update
        of the cotangent Laplacian coordinates) or ``dual`` (iterative dual Laplacian).
    constraints, weight : see :class:`LaplacianSystem`.
    tol, max_iter : stopping rule of the iterative methods.
    """

    def __init__(self, V0, F, handles, method: str = "plain", constraints: str = "hard", weight: float = 1.0,
                 tol: float = 1e-3, max_iter: int = 30):
        if method not in DEFORM_METHODS:
            raise FacesynthError(f"laplacian: unknown method {method!r} (choose from {', '.join(DEFORM_METHODS)})")
        self.V0 = np.asarray(V0, float)
        self.F = np.asarray(F, np.int64)
        self.method, self.tol, self.max_iter = method, tol, max_iter
        if method == "plain":
            self.coords = None
            self.op = cotangent_laplacian(self.V0, self.F)
            self.delta0 = np.asarray(self.op @ self.V0)
        else:
            self.coords = (DualCoordinates if method == "dual" else PrimalCoordinates)(self.V0, self.F)
            self.op, self.delta0 = self.coords.op, self.coords.delta0
        self.system = LaplacianSystem(self.op, handles, constraints, weight)
        self.handles = self.system.handles

    def deform(self, targets: np.ndarray, return_info: bool = False):
        """Deformed vertices (N, 3) with ``V[handles]`` on ``targets`` (H, 3) (exactly for
        hard constraints)."""
        targets = np.asarray(targets, float)
        if targets.shape != (len(self.handles), 3):
            raise FacesynthError(f"laplacian: targets must be ({len(self.handles)}, 3), got {targets.shape}")
        V = self.system.solve(self.delta0, targets)
        info = DeformInfo()
        if self.method != "plain":
            info.converged = False
            floor = 1e-8 * np.linalg.norm(self.V0 - self.V0.mean(axis=0))  # "no deformation" level
            for k in range(self.max_iter):
                V_new = self.system.solve(self.coords.delta(V), targets)
                rel = float(np.linalg.norm(V_new - V) / max(np.linalg.norm(V_new - self.V0), floor))
                V = V_new
                info.rel_change.append(rel)
                info.iterations = k + 2
                if rel < self.tol or not np.isfinite(rel):
                    info.converged = bool(np.isfinite(rel))
                    break
        return (V, info) if return_info else V
