"""Generalised Procrustes analysis (similarity alignment: :mod:`facesynth.geometry`).

Array-level: these functions know nothing about faces. Points are (x, y).

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
training and application", CVIU 61(1), 1995 (generalised Procrustes alignment).
"""

from __future__ import annotations

import numpy as np

from facesynth.geometry import apply_affine, similarity_fit


def normalise_shape(shape: np.ndarray) -> np.ndarray:
    """Centre (K, 2) points on the origin and scale them to unit Frobenius norm."""
    c = shape - shape.mean(0)
    return c / np.linalg.norm(c)


def generalised_procrustes(
    shapes: np.ndarray, max_iter: int = 100, tol: float = 1e-10
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised Procrustes alignment under similarity transforms.

    Parameters
    ----------
    shapes : np.ndarray
        (N, K, 2) point sets.
    max_iter, tol : int, float
        Iterate until the mean moves by less than ``tol`` (Frobenius norm).

    Returns
    -------
    aligned : np.ndarray
        (N, K, 2) float64 shapes similarity-aligned to the mean.
    mean : np.ndarray
        (K, 2) float64 mean shape, centred, unit norm, rotated like the first shape.
    """
    shapes = np.asarray(shapes, np.float64)
    ref = normalise_shape(shapes[0])
    mean = ref
    for _ in range(max_iter):
        aligned = apply_affine(shapes, similarity_fit(shapes, mean[None]))
        new = normalise_shape(aligned.mean(0))
        new = apply_affine(new, similarity_fit(new, ref))  # fix the gauge: rotation of the first shape
        new = normalise_shape(new)
        delta = np.linalg.norm(new - mean)
        mean = new
        if delta < tol:
            break
    aligned = apply_affine(shapes, similarity_fit(shapes, mean[None]))
    return aligned, mean
