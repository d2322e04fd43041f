"""Generalised Procrustes analysis: the functions live in the ground module
:mod:`facesynth.geometry` (numpy only, so that the neutral-frame rule and the torch-free
runtime's retargeting can use them); re-exported here under the model's import path.

References
----------
T. F. Cootes, C. J. Taylor, D. H. Cooper, J. Graham, "Active shape models - their
training and application", CVIU 61(1), 1995 (generalised Procrustes alignment).
"""

from facesynth.geometry import generalised_procrustes, normalise_shape

__all__ = ["generalised_procrustes", "normalise_shape"]
