"""Readers and writers registered by file extension (as menpo does, without its
hidden (y, x) convention: everything here is (x, y), 0-based).

``load_sequence(path)`` accepts:

* a folder in the ingest layout (``landmarks.npy`` + ``meta.json`` + a video), the
  layout written by ``facesynth ingest`` and used by ``shared/data/faces/<clip>``;
* a folder of images each with a ``.pts`` file of the same stem;
* a ``.npy`` array (T, 68, 2) of landmarks (landmark-only sequence);
* a ``.npz`` archive with ``landmarks`` (T, 68, 2) and optionally ``frames`` (T, H, W, 3) uint8.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from facesynth.data.frames import ArrayFrames, ImageFiles, VideoFrames
from facesynth.data.pts import read_pts, write_pts
from facesynth.data.sequence import FaceSequence, validate_landmarks
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

READERS: dict[str, Callable[[Path], FaceSequence]] = {}
WRITERS: dict[str, Callable[[Path, np.ndarray], None]] = {}


def register_reader(*extensions: str):
    """Decorator: register a reader for file extensions (``"/"`` stands for folders)."""

    def deco(fn):
        for ext in extensions:
            READERS[ext.lower()] = fn
        return fn

    return deco


def register_writer(*extensions: str):
    """Decorator: register a landmark writer for extensions (``"/"`` for a folder of .pts)."""

    def deco(fn):
        for ext in extensions:
            WRITERS[ext.lower()] = fn
        return fn

    return deco


def load_sequence(path: str | os.PathLike) -> FaceSequence:
    """Read a :class:`FaceSequence` from ``path``, choosing the reader by extension."""
    path = Path(path)
    if not path.exists():
        raise FacesynthError(f"{path}: no such file or folder")
    key = "/" if path.is_dir() else path.suffix.lower()
    if key not in READERS:
        raise FacesynthError(f"{path}: unknown format '{key}' (readable: {', '.join(sorted(READERS))})")
    return READERS[key](path)


def load_landmarks(path: str | os.PathLike) -> np.ndarray:
    """Landmarks (T, 68, 2) float32 from any readable source (NaN rows kept)."""
    path = Path(path)
    if path.is_dir() and (path / "landmarks.npy").is_file():
        path = path / "landmarks.npy"
    if path.suffix.lower() == ".npy":
        return validate_landmarks(_np_load(path), str(path), allow_nan_rows=True)
    return load_sequence(path).landmarks


def save_landmarks(path: str | os.PathLike, landmarks: np.ndarray) -> None:
    """Write landmarks (T, 68, 2), choosing the writer by extension; atomic."""
    path = Path(path)
    key = "/" if (path.is_dir() or not path.suffix) else path.suffix.lower()
    if key not in WRITERS:
        raise FacesynthError(f"{path}: no landmark writer for '{key}' (writable: {', '.join(sorted(WRITERS))})")
    WRITERS[key](path, validate_landmarks(landmarks, str(path), allow_nan_rows=True))


def _np_load(path: Path):
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FacesynthError(f"{path}: not a readable numpy file ({exc})") from None


@register_reader(".npy")
def _read_npy(path: Path) -> FaceSequence:
    return FaceSequence.from_arrays(_np_load(path), where=str(path), name=path.stem, meta={"source": str(path)})


@register_reader(".npz")
def _read_npz(path: Path) -> FaceSequence:
    z = _np_load(path)
    if "landmarks" not in z.files:
        raise FacesynthError(f"{path}: .npz must hold an array named 'landmarks' (T, 68, 2); found {z.files}")
    frames = ArrayFrames(z["frames"]) if "frames" in z.files else None
    fps = float(z["fps"]) if "fps" in z.files else 30.0
    return FaceSequence.from_arrays(z["landmarks"], frames, where=str(path), name=path.stem, fps=fps, meta={"source": str(path)})


@register_reader("/")
def _read_folder(path: Path) -> FaceSequence:
    if (path / "landmarks.npy").is_file():
        return _read_ingest_folder(path)
    pts = sorted(path.glob("*.pts"))
    if pts:
        return _read_pts_folder(path, pts)
    raise FacesynthError(f"{path}: folder has neither landmarks.npy (ingest layout) nor .pts files")


def array_sha256(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (``facesynth ingest`` records it in
    meta.json; loading checks it, so landmarks and meta from different runs never pair)."""
    a = np.ascontiguousarray(a)
    return hashlib.sha256(f"{a.dtype.str}{a.shape}".encode() + a.tobytes()).hexdigest()


def _check_ingest_pair(path: Path, lm: np.ndarray, meta: dict) -> None:
    info = meta.get("landmarks") if isinstance(meta.get("landmarks"), dict) else {}
    where = path / "landmarks.npy"
    if "shape" in info and list(np.shape(lm)) != list(info["shape"]):
        raise FacesynthError(f"{where}: shape {list(np.shape(lm))} differs from meta.json's {info['shape']} "
                             "(the folder mixes files of two ingests)")
    if info.get("sha256") and array_sha256(lm) != info["sha256"]:
        raise FacesynthError(f"{where}: content differs from meta.json's landmarks SHA-256 "
                             "(the folder mixes files of two ingests, or the landmarks were edited)")


def _read_ingest_folder(path: Path) -> FaceSequence:
    meta: dict = {}
    if (path / "meta.json").is_file():
        try:
            meta = json.loads((path / "meta.json").read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise FacesynthError(f"{path / 'meta.json'}: invalid JSON ({exc})") from None
        if not isinstance(meta, dict):
            raise FacesynthError(f"{path / 'meta.json'}: expected a JSON object")
    video = meta.get("video", {}) if isinstance(meta.get("video"), dict) else {}
    candidates = [path / video["file"]] if video.get("file") else []
    if video.get("path"):
        candidates.append(Path(video["path"]))
    candidates.append(path / "video.mp4")
    video_path = next((c for c in candidates if c.is_file()), None)
    frames = VideoFrames(video_path) if video_path is not None else None
    fps = float(video.get("fps") or (frames.fps if frames else 30.0) or 30.0)
    meta = {**meta, "source": str(path)}
    if video.get("sha256"):
        meta["source_sha256"] = video["sha256"]
    lm = _np_load(path / "landmarks.npy")
    _check_ingest_pair(path, lm, meta)
    return FaceSequence.from_arrays(lm, frames, where=str(path / "landmarks.npy"), name=path.name, fps=fps, meta=meta)


def _read_pts_folder(path: Path, pts: list[Path]) -> FaceSequence:
    images = []
    for p in pts:
        img = next((p.with_suffix(e) for e in IMAGE_EXTENSIONS if p.with_suffix(e).is_file()), None)
        if img is None:
            raise FacesynthError(f"{p}: no image with the same name ({'/'.join(IMAGE_EXTENSIONS)})")
        images.append(img)
    lm = np.stack([read_pts(p) for p in pts])
    return FaceSequence.from_arrays(lm, ImageFiles(images), where=str(path), name=path.name, meta={"source": str(path)})


@register_writer(".npy")
def _write_npy(path: Path, lm: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, lm)


@register_writer(".npz")
def _write_npz(path: Path, lm: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, landmarks=lm)


@register_writer("/")
def _write_pts_folder(path: Path, lm: np.ndarray) -> None:
    path.mkdir(parents=True, exist_ok=True)
    width = max(6, len(str(len(lm))))
    for i, frame in enumerate(lm):
        if np.isfinite(frame).all():
            write_pts(path / f"{i:0{width}d}.pts", frame)
