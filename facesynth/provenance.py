"""What every artifact records: config, package versions and a data fingerprint."""

from __future__ import annotations

import hashlib
import platform
from importlib import metadata
from pathlib import Path

import numpy as np

_PACKAGES = (
    "facesynth", "torch", "numpy", "scipy", "scikit-learn", "opencv-contrib-python-headless",
    "onnxruntime", "onnx", "hydra-core", "trimesh", "kornia", "constriction", "dlib-bin",
)


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape results (absent ones are left out)."""
    out = {"python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def array_fingerprint(*arrays: np.ndarray) -> str:
    """SHA-256 (first 16 hex digits) over the dtype, shape and bytes of ``arrays``."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Full SHA-256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
