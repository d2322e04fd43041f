"""One way to store a fitted model: a folder with a ``.safetensors`` file (numpy arrays) and
a JSON manifest that names the format and its version, the facesynth and
package versions, the creation time and the SHA-256 of the tensor file.

The face model (:mod:`facesynth.model.artifact`), the SADM regressor
(:mod:`facesynth.sadm.fit`) and the ERI model (:mod:`facesynth.eri.model`) all use it, so
that each checks its format, version and integrity the same way and says the same clear
thing when a file is missing, unreadable, from another version or altered.
"""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np
from safetensors.numpy import load_file, save_file

from facesynth import __version__
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path, read_json_object, write_json
from facesynth.provenance import package_versions

T = TypeVar("T")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_artifact(directory: str | os.PathLike, tensors_file: str, manifest_file: str, tensors: dict[str, np.ndarray],
                  manifest: dict, fmt: str, version: int) -> Path:
    """Write ``directory/tensors_file`` and ``directory/manifest_file`` (each atomically, the
    manifest last, so a folder whose manifest exists has its tensors).

    Parameters
    ----------
    tensors_file, manifest_file : file names, e.g. "face_model.safetensors", "face_model.json"
    tensors : name -> numpy array (stored contiguous, dtype kept)
    manifest : JSON-serialisable fields of the format; ``format``, ``format_version``,
        ``facesynth_version``, ``created``, ``packages`` and ``tensors_sha256`` are added
        unless given.
    fmt, version : the format name and version that :func:`read_artifact` checks.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tpath = d / tensors_file
    with atomic_path(tpath) as tmp:
        save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, str(tmp))
    head = {"format": fmt, "format_version": version, "facesynth_version": __version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    tail = {"packages": package_versions(), "tensors_sha256": _sha256(tpath)}
    write_json(d / manifest_file, {**head, **manifest, **{k: v for k, v in tail.items() if k not in manifest}})
    return d


def read_manifest(directory: str | os.PathLike, manifest_file: str, fmt: str, version: int, what: str) -> dict:
    """The manifest ``directory/manifest_file``, checked: present, valid JSON, format ``fmt`` of
    ``version``. ``what`` names the artifact in messages (e.g. "face model")."""
    d = Path(directory)
    path = d / manifest_file
    if not path.is_file():
        article = "an" if what[:1].lower() in "aeiou" else "a"
        raise FacesynthError(f"{d}: not {article} {what} directory ({path.name} missing)")
    manifest = read_json_object(path)
    if manifest.get("format") != fmt:
        raise FacesynthError(f"{path}: format is {manifest.get('format')!r}, expected {fmt!r}")
    if manifest.get("format_version") != version:
        raise FacesynthError(
            f"{path}: {what} format version {manifest.get('format_version')} (written by facesynth "
            f"{manifest.get('facesynth_version')}) is not supported by facesynth {__version__}, which reads "
            f"version {version}; refit the model with this version"
        )
    return manifest


def read_tensors(directory: str | os.PathLike, tensors_file: str, manifest: dict, what: str) -> dict[str, np.ndarray]:
    """The arrays of ``directory/tensors_file``, checked: the manifest records their SHA-256
    (mandatory) and it matches; the file parses; every float tensor is finite."""
    path = Path(directory) / tensors_file
    if not path.is_file():
        raise FacesynthError(f"{path}: {what} tensors missing")
    want = manifest.get("tensors_sha256")
    if not isinstance(want, str) or len(want) != 64:
        raise FacesynthError(f"{path}: the manifest records no valid 'tensors_sha256' for the {what} tensors "
                             "(integrity cannot be checked; refit or re-save the model)")
    if _sha256(path) != want:
        raise FacesynthError(f"{path}: {what} tensors altered or corrupt (SHA-256 differs from the manifest's)")
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # safetensors raises several types for corrupt files
        raise FacesynthError(f"{path}: unreadable {what} tensors ({exc})") from None
    for name, arr in tensors.items():
        if arr.dtype.kind in "fc" and not np.isfinite(arr).all():
            raise FacesynthError(f"{path}: {what} tensor {name!r} holds NaN or infinite values")
    return tensors


def rebuild(path: str | os.PathLike, what: str, build: Callable[[], T]) -> T:
    """``build()``, with the errors that tensors of the wrong shape, dtype or name raise
    (KeyError, TypeError, ValueError, IndexError, RuntimeError) turned into one
    FacesynthError naming ``path``."""
    try:
        return build()
    except KeyError as exc:
        raise FacesynthError(f"{path}: {what} tensor or field {exc} missing") from None
    except (TypeError, ValueError, IndexError, RuntimeError) as exc:
        first = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
        raise FacesynthError(f"{path}: {what} tensors do not fit together ({first})") from None


def manifest_field(manifest: dict, key: str, path: str | os.PathLike):
    """``manifest[key]``, or FacesynthError naming the missing field and the file."""
    try:
        return manifest[key]
    except KeyError:
        raise FacesynthError(f"{path}: manifest lacks the field {key!r}") from None
