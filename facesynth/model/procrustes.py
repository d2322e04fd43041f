"""Generalised Procrustes analysis: now in the ground module :mod:`facesynth.geometry`
(numpy only, so that the torch-free runtime's retargeting can use it); re-exported here."""

from facesynth.geometry import generalised_procrustes, normalise_shape

__all__ = ["generalised_procrustes", "normalise_shape"]
