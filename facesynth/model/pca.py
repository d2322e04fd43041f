"""PCA on vectors: the array-level linear model under both the shape and the appearance
model (x = mean + P b), as in Cootes et al.'s point distribution and appearance models."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facesynth.errors import FacesynthError


@dataclass
class PCAModel:
    """A linear subspace model.

    Attributes
    ----------
    mean : np.ndarray
        float32 (D,).
    components : np.ndarray
        float32 (K, D), orthonormal rows, ordered by decreasing variance.
    eigenvalues : np.ndarray
        float64 (K,): variance along each component (divided by N - 1).
    total_variance : float
        Sum of all eigenvalues of the training data (kept and discarded).
    """

    mean: np.ndarray
    components: np.ndarray
    eigenvalues: np.ndarray
    total_variance: float

    @classmethod
    def fit(cls, data: np.ndarray, n_components: int | None = None, variance: float | None = 0.98) -> "PCAModel":
        """Fit on (N, D) samples, keeping ``n_components`` or the smallest number of
        components that explains ``variance`` (a fraction in (0, 1]) of the total."""
        x = np.asarray(data)
        if x.ndim != 2 or len(x) < 2:
            raise FacesynthError(f"PCA needs (N >= 2, D) data, got shape {x.shape}")
        if not np.isfinite(x).all():
            raise FacesynthError("PCA data contain NaN/inf")
        n = len(x)
        wide = x.shape[1] > n
        # Wide data (textures: N x C*M) stays in float32 to bound memory (one centred copy);
        # the small N x N eigenproblem is solved in float64.
        x = x.astype(np.float32 if wide and x.dtype == np.float32 else np.float64, copy=False)
        mean = x.mean(0, dtype=np.float64)
        xc = x - mean.astype(x.dtype)
        if wide:  # Gram trick: eigen-decompose the N x N matrix
            evals, u = np.linalg.eigh((xc @ xc.T).astype(np.float64))
            order = np.argsort(evals)[::-1]
            evals, u = np.clip(evals[order], 0, None), u[:, order]
            keep = evals > evals[0] * 1e-12
            comps = (u[:, keep].T.astype(xc.dtype) @ xc) / np.sqrt(evals[keep]).astype(xc.dtype)[:, None]
            evals = evals[keep]
        else:
            _, s, vt = np.linalg.svd(xc, full_matrices=False)
            evals, comps = s**2, vt
        evals = evals / (n - 1)
        total = float(evals.sum())
        k = _choose_k(evals, total, n_components, variance)
        return cls(mean.astype(np.float32), comps[:k].astype(np.float32), evals[:k], total)

    @property
    def n_components(self) -> int:
        return len(self.components)

    @property
    def explained_variance_ratio(self) -> float:
        return float(self.eigenvalues.sum() / self.total_variance) if self.total_variance > 0 else 1.0

    def project(self, x: np.ndarray) -> np.ndarray:
        """Parameters b = P (x - mean): (N, D) -> (N, K)."""
        return (np.asarray(x, np.float32) - self.mean) @ self.components.T

    def reconstruct(self, b: np.ndarray) -> np.ndarray:
        """x = mean + P^T b: (N, K) -> (N, D)."""
        return self.mean + np.asarray(b, np.float32) @ self.components

    def clamp(self, b: np.ndarray, k: float = 3.0) -> np.ndarray:
        """Limit each parameter to +-k sqrt(eigenvalue): (N, K) -> (N, K)."""
        lim = (k * np.sqrt(self.eigenvalues)).astype(np.float32)
        return np.clip(b, -lim, lim)

    def truncate(self, k: int) -> "PCAModel":
        """The model with only its first ``k`` components."""
        return PCAModel(self.mean, self.components[:k], self.eigenvalues[:k], self.total_variance)


def _choose_k(evals: np.ndarray, total: float, n_components: int | None, variance: float | None) -> int:
    if n_components is not None:
        if n_components < 1:
            raise FacesynthError(f"n_components must be >= 1, got {n_components}")
        return min(int(n_components), len(evals))
    if variance is None or not 0 < variance <= 1:
        raise FacesynthError(f"variance must be a fraction in (0, 1], got {variance}")
    if total == 0:
        return 1
    return int(min(len(evals), np.searchsorted(np.cumsum(evals) / total, variance - 1e-12) + 1))
