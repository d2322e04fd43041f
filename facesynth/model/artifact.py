"""Saving and loading a fitted face model: one directory with ``face_model.safetensors``
and a JSON manifest (config, landmark scheme, reference size, package versions, data
fingerprint), written and checked by :mod:`facesynth.artifact`."""

from __future__ import annotations

import os
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from facesynth.artifact import manifest_field, read_tensors, save_artifact
from facesynth.artifact import read_manifest as _read_manifest
from facesynth.errors import FacesynthError
from facesynth.landmarks import DEFAULT_SCHEME
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.pca import PCAModel
from facesynth.model.reference import ReferenceFrame

FORMAT = "facesynth.face_model"
FORMAT_VERSION = 1
LANDMARK_SCHEME = DEFAULT_SCHEME.name
TENSORS, MANIFEST = "face_model.safetensors", "face_model.json"
WHAT = "face model"


def save_face_model(model: FaceModel, directory: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write ``model`` into ``directory`` (created). Files are written atomically."""
    tensors = {
        "shape_mean": model.shape_pca.mean,
        "shape_components": model.shape_pca.components,
        "shape_eigenvalues": model.shape_pca.eigenvalues.astype(np.float64),
        "appearance_mean": model.appearance_pca.mean,
        "appearance_components": model.appearance_pca.components,
        "appearance_eigenvalues": model.appearance_pca.eigenvalues.astype(np.float64),
        "reference_points": model.reference.points,
        "triangles": model.reference.triangles.astype(np.int64),
        "span": model.span.astype(np.int64),
    }
    return save_artifact(directory, TENSORS, MANIFEST, tensors, {
        "landmark_scheme": LANDMARK_SCHEME,
        "reference_size": list(model.reference.size),
        "config": asdict(model.config),
        "shape_total_variance": model.shape_pca.total_variance,
        "appearance_total_variance": model.appearance_pca.total_variance,
        "data_fingerprint": model.fingerprint,
        "meta": model.meta,
        **(extra or {}),
    }, FORMAT, FORMAT_VERSION)


def read_manifest(directory: str | os.PathLike) -> dict:
    """The checked manifest of a face model directory."""
    manifest = _read_manifest(directory, MANIFEST, FORMAT, FORMAT_VERSION, WHAT)
    if manifest.get("landmark_scheme") != LANDMARK_SCHEME:
        raise FacesynthError(f"{Path(directory) / MANIFEST}: landmark scheme {manifest.get('landmark_scheme')!r}, "
                             f"expected {LANDMARK_SCHEME!r}")
    return manifest


def load_face_model(directory: str | os.PathLike) -> FaceModel:
    """Load a model written by :func:`save_face_model`."""
    d = Path(directory)
    manifest = read_manifest(d)
    t = read_tensors(d, TENSORS, manifest, WHAT)
    where = d / MANIFEST
    known = {f.name for f in fields(FaceModelConfig)}
    cfg = FaceModelConfig(**{k: v for k, v in manifest_field(manifest, "config", where).items() if k in known})
    try:
        ref = ReferenceFrame(t["reference_points"], tuple(manifest_field(manifest, "reference_size", where)), t["triangles"])
        return FaceModel(
            config=cfg,
            shape_pca=PCAModel(t["shape_mean"], t["shape_components"], t["shape_eigenvalues"],
                               manifest_field(manifest, "shape_total_variance", where)),
            reference=ref,
            appearance_pca=PCAModel(t["appearance_mean"], t["appearance_components"], t["appearance_eigenvalues"],
                                    manifest_field(manifest, "appearance_total_variance", where)),
            span=t["span"],
            fingerprint=manifest_field(manifest, "data_fingerprint", where),
            meta=manifest.get("meta", {}),
        )
    except KeyError as exc:
        raise FacesynthError(f"{d / TENSORS}: tensor {exc} missing") from None
