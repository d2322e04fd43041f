"""Saving and loading a fitted face model: one directory with ``face_model.safetensors``
and a JSON manifest (config, landmark scheme, reference size, package versions, data
fingerprint), written and checked by :mod:`facesynth.artifact`."""

from __future__ import annotations

import os
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np

from facesynth.artifact import manifest_field, read_tensors, rebuild, save_artifact
from facesynth.artifact import read_manifest as _read_manifest
from facesynth.errors import FacesynthError
from facesynth.landmarks import SCHEMES, get_scheme
from facesynth.model.detail import BANK_TENSORS, check_bank
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.pca import PCAModel
from facesynth.model.reference import ReferenceFrame

FORMAT = "facesynth.face_model"
FORMAT_VERSION = 1
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
    denoise = {}
    if model.denoise_pca is not None:  # absent: landmarks used as given (also every model before it existed)
        tensors.update(denoise_mean=model.denoise_pca.mean, denoise_components=model.denoise_pca.components,
                       denoise_eigenvalues=model.denoise_pca.eigenvalues.astype(np.float64))
        denoise = {"denoise_total_variance": model.denoise_pca.total_variance}
    if model.restore_kernel is not None:  # absent: no restoration filter
        tensors["restore_kernel"] = np.asarray(model.restore_kernel, np.float32)
    if model.restore_offset is not None:  # absent: no restoration of the mean beyond the kernel's
        tensors["restore_offset"] = np.asarray(model.restore_offset, np.float32)
    if model.detail_bank is not None:  # absent: no example-based detail
        tensors.update(model.detail_bank)
    return save_artifact(directory, TENSORS, MANIFEST, tensors, {
        "landmark_scheme": model.scheme,
        "reference_size": list(model.reference.size),
        "config": asdict(model.config),
        "shape_total_variance": model.shape_pca.total_variance,
        "appearance_total_variance": model.appearance_pca.total_variance,
        "data_fingerprint": model.fingerprint,
        "meta": model.meta,
        **denoise,
        **(extra or {}),
    }, FORMAT, FORMAT_VERSION)


def read_manifest(directory: str | os.PathLike) -> dict:
    """The checked manifest of a face model directory (its ``landmark_scheme`` one of
    :data:`facesynth.landmarks.SCHEMES`)."""
    manifest = _read_manifest(directory, MANIFEST, FORMAT, FORMAT_VERSION, WHAT)
    if manifest.get("landmark_scheme") not in SCHEMES:
        raise FacesynthError(f"{Path(directory) / MANIFEST}: landmark scheme {manifest.get('landmark_scheme')!r}, "
                             f"expected one of {', '.join(sorted(SCHEMES))}")
    return manifest


def load_face_model(directory: str | os.PathLike) -> FaceModel:
    """Load a model written by :func:`save_face_model`; FacesynthError for a missing,
    altered, non-finite or inconsistent artifact."""
    d = Path(directory)
    manifest = read_manifest(d)
    t = read_tensors(d, TENSORS, manifest, WHAT)
    where = d / MANIFEST
    known = {f.name for f in fields(FaceModelConfig)}

    def build() -> FaceModel:
        cfg = FaceModelConfig(**{k: v for k, v in dict(manifest_field(manifest, "config", where)).items() if k in known})
        ref = ReferenceFrame(t["reference_points"], check_size(manifest_field(manifest, "reference_size", where)), t["triangles"])
        model = FaceModel(
            config=cfg,
            shape_pca=PCAModel(t["shape_mean"], t["shape_components"], t["shape_eigenvalues"],
                               float(manifest_field(manifest, "shape_total_variance", where))),
            reference=ref,
            appearance_pca=PCAModel(t["appearance_mean"], t["appearance_components"], t["appearance_eigenvalues"],
                                    float(manifest_field(manifest, "appearance_total_variance", where))),
            span=t["span"],
            fingerprint=manifest_field(manifest, "data_fingerprint", where),
            meta=manifest.get("meta", {}),
            scheme=manifest["landmark_scheme"],
            denoise_pca=None if "denoise_mean" not in t else PCAModel(
                t["denoise_mean"], t["denoise_components"], t["denoise_eigenvalues"],
                float(manifest_field(manifest, "denoise_total_variance", where))),
            restore_kernel=t.get("restore_kernel"),
            restore_offset=t.get("restore_offset"),
            detail_bank={k: t[k] for k in BANK_TENSORS if k in t} if BANK_TENSORS[0] in t else None,
        )
        check_face_model(model)
        return model

    return rebuild(d / TENSORS, WHAT, build)


MAX_REFERENCE_SIDE = 4096  # pixels; a reference frame is ~100-300 px wide


def check_size(size) -> tuple[int, int]:
    """A reference (H, W): two integers in [1, MAX_REFERENCE_SIDE], else ValueError."""
    size = tuple(size)
    if len(size) != 2 or not all(isinstance(v, int) and 1 <= v <= MAX_REFERENCE_SIDE for v in size):
        raise ValueError(f"reference_size must be two integers in [1, {MAX_REFERENCE_SIDE}], got {list(size)}")
    return size


def check_pca(pca: PCAModel, name: str, dim: int | None = None) -> None:
    """mean (D,), components (K, D), eigenvalues (K,) non-negative; D == ``dim`` when given. ValueError otherwise."""
    d = pca.mean.shape[0] if pca.mean.ndim == 1 else -1
    if (d < 1 or pca.components.ndim != 2 or pca.components.shape[1] != d or pca.eigenvalues.shape != pca.components.shape[:1]
            or (dim is not None and d != dim) or (pca.eigenvalues < 0).any()):
        raise ValueError(f"{name}: mean {pca.mean.shape}, components {pca.components.shape}, eigenvalues "
                         f"{pca.eigenvalues.shape} do not form a PCA model" + (f" of dimension {dim}" if dim else ""))


def check_reference(ref: ReferenceFrame, n_points: int) -> None:
    """points (P, 2), triangles (T, 3) integer indices into points. ValueError otherwise."""
    tri = ref.triangles
    if ref.points.shape != (n_points, 2):
        raise ValueError(f"reference_points: expected ({n_points}, 2), got {ref.points.shape}")
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.dtype.kind not in "iu" or len(tri) < 1 or tri.min() < 0 or tri.max() >= n_points:
        raise ValueError(f"triangles: expected (T, 3) indices in [0, {n_points}), got {tri.dtype} {tri.shape}")


def check_face_model(model: FaceModel) -> None:
    """The tensors of a rebuilt face model fit together; ValueError naming the first that does not."""
    n_points = get_scheme(model.scheme).n_points
    check_pca(model.shape_pca, "shape PCA", 2 * n_points)
    check_reference(model.reference, n_points)
    if model.span.shape != (len(model.reference.triangles), 2):
        raise ValueError(f"span: expected ({len(model.reference.triangles)}, 2), got {model.span.shape}")
    check_pca(model.appearance_pca, "appearance PCA", model.n_channels * model.n_pixels)
    if model.denoise_pca is not None:
        check_pca(model.denoise_pca, "denoise PCA", 2 * n_points)
    if model.detail_bank is not None:
        check_bank(model.detail_bank, n_points, model.n_channels, model.n_pixels)
    k = model.restore_kernel
    if k is not None and (k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 != 1):
        raise ValueError(f"restore_kernel: expected an odd square (k, k) kernel, got {k.shape}")
    o = model.restore_offset
    if o is not None and o.shape != (model.n_channels * model.n_pixels,):
        raise ValueError(f"restore_offset: expected ({model.n_channels * model.n_pixels},), a texture, got {o.shape}")
