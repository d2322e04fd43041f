"""Face model: Procrustes-aligned shape PCA and appearance PCA on piecewise-affine
warped textures (array-level PCA and Procrustes, face-level FaceModel)."""

from facesynth.geometry import similarity_fit
from facesynth.model.artifact import load_face_model, save_face_model
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.pca import PCAModel
from facesynth.model.procrustes import generalised_procrustes
from facesynth.model.reference import ReferenceFrame

__all__ = [
    "FaceModel", "FaceModelConfig", "PCAModel", "ReferenceFrame", "generalised_procrustes",
    "load_face_model", "save_face_model", "similarity_fit",
]
