"""Saving and loading a fitted face model: one directory with ``face_model.safetensors``
and a JSON manifest (config, landmark scheme, reference size, package versions, data
fingerprint). Loading refuses artifacts of another format version with a clear message."""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file, save_file

from facesynth import __version__
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path, write_json
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.pca import PCAModel
from facesynth.model.reference import ReferenceFrame
from facesynth.provenance import package_versions

FORMAT = "facesynth.face_model"
FORMAT_VERSION = 1
LANDMARK_SCHEME = "ibug68"
TENSORS = "face_model.safetensors"
MANIFEST = "face_model.json"


def save_face_model(model: FaceModel, directory: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write ``model`` into ``directory`` (created). Files are written atomically."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
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
    with atomic_path(d / TENSORS) as tmp:
        save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, str(tmp))
    write_json(d / MANIFEST, {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "facesynth_version": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "landmark_scheme": LANDMARK_SCHEME,
        "reference_size": list(model.reference.size),
        "config": asdict(model.config),
        "shape_total_variance": model.shape_pca.total_variance,
        "appearance_total_variance": model.appearance_pca.total_variance,
        "data_fingerprint": model.fingerprint,
        "packages": package_versions(),
        "meta": model.meta,
        **(extra or {}),
    })
    return d


def read_manifest(directory: str | os.PathLike) -> dict:
    """The checked manifest of a face model directory."""
    d = Path(directory)
    path = d / MANIFEST
    if not path.is_file():
        raise FacesynthError(f"{d}: not a face model directory ({MANIFEST} missing)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise FacesynthError(f"{path}: invalid JSON ({exc})") from None
    if manifest.get("format") != FORMAT:
        raise FacesynthError(f"{path}: format is {manifest.get('format')!r}, expected {FORMAT!r}")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise FacesynthError(
            f"{path}: face model format version {manifest.get('format_version')} (written by facesynth "
            f"{manifest.get('facesynth_version')}) is not supported by facesynth {__version__}, which reads "
            f"version {FORMAT_VERSION}; refit the model with this version"
        )
    if manifest.get("landmark_scheme") != LANDMARK_SCHEME:
        raise FacesynthError(f"{path}: landmark scheme {manifest.get('landmark_scheme')!r}, expected {LANDMARK_SCHEME!r}")
    return manifest


def load_face_model(directory: str | os.PathLike) -> FaceModel:
    """Load a model written by :func:`save_face_model`."""
    d = Path(directory)
    manifest = read_manifest(d)
    try:
        t = load_file(str(d / TENSORS))
    except Exception as exc:  # safetensors raises several types for corrupt files
        raise FacesynthError(f"{d / TENSORS}: unreadable model tensors ({exc})") from None
    known = {f.name for f in fields(FaceModelConfig)}
    cfg = FaceModelConfig(**{k: v for k, v in manifest["config"].items() if k in known})
    ref = ReferenceFrame(t["reference_points"], tuple(manifest["reference_size"]), t["triangles"])
    return FaceModel(
        config=cfg,
        shape_pca=PCAModel(t["shape_mean"], t["shape_components"], t["shape_eigenvalues"], manifest["shape_total_variance"]),
        reference=ref,
        appearance_pca=PCAModel(
            t["appearance_mean"], t["appearance_components"], t["appearance_eigenvalues"], manifest["appearance_total_variance"]
        ),
        span=t["span"],
        fingerprint=manifest["data_fingerprint"],
        meta=manifest.get("meta", {}),
    )
