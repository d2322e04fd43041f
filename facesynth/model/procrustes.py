"""Generalised Procrustes analysis (similarity alignment: :mod:`facesynth.geometry`).

Array-level: these functions know nothing about faces. Points are (x, y).

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
training and application", CVIU 61(1), 1995 (generalised Procrustes alignment).
"""

from __future__ import annotations

# the functions live in the ground (facesynth.geometry) so that the data layer's neutral-frame
# choice (facesynth.data.neutral) can use them; this module keeps the model's import path
from facesynth.geometry import generalised_procrustes, normalise_shape

__all__ = ["generalised_procrustes", "normalise_shape"]
