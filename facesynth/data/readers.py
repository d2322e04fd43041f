"""Readers and writers registered by file extension (as menpo does, without its
hidden (y, x) convention: everything here is (x, y), 0-based).

``load_sequence(path)`` accepts:

* a folder in the ingest layout (``landmarks.npy`` + ``meta.json`` + a video), the
  layout written by ``facesynth ingest`` and used by ``shared/data/faces/<clip>``;
* a folder of images each with a ``.pts`` file of the same stem;
* a ``.npy`` array (T, P, 2) of landmarks (landmark-only sequence);
* a ``.npz`` archive with ``landmarks`` (T, P, 2) and optionally ``frames`` (T, H, W, 3) uint8.

The landmark scheme is ``meta.json``'s ``landmarks.scheme`` in the ingest layout; without
it (the shipped clips, bare arrays, .pts) it is the registered scheme with P points
(68 -> ``ibug68``, 478 -> ``mediapipe478``). ``scheme=`` asks for a scheme: landmarks
already in it load as they are, others are mapped when a mapping exists (478 -> 68,
approximate: docs/landmarks.md) and are an error otherwise.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Callable

import numpy as np

from facesynth.data.frames import ArrayFrames, ImageFiles, VideoFrames
from facesynth.data.meta import read_ingest_meta
from facesynth.data.pts import read_pts, write_pts
from facesynth.data.sequence import FaceSequence, validate_landmarks
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path
from facesynth.landmarks import SCHEMES, get_scheme, scheme_for_points

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


def load_sequence(path: str | os.PathLike, scheme: str | None = None) -> FaceSequence:
    """Read a :class:`FaceSequence` from ``path``, choosing the reader by extension.

    ``scheme``: None keeps the stored landmark scheme (``seq.scheme``); a name maps the
    landmarks to it (:meth:`FaceSequence.to_scheme`), e.g. ``scheme="ibug68"`` gives every
    68-point stage a 478-point folder."""
    path = Path(path)
    if scheme is not None:
        get_scheme(scheme)  # an unknown name fails before any reading
    if not path.exists():
        raise FacesynthError(f"{path}: no such file or folder")
    key = "/" if path.is_dir() else path.suffix.lower()
    if key not in READERS:
        raise FacesynthError(f"{path}: unknown format '{key}' (readable: {', '.join(sorted(READERS))})")
    seq = READERS[key](path)
    return seq if scheme is None else seq.to_scheme(scheme)


def load_landmarks(path: str | os.PathLike, scheme: str | None = None) -> np.ndarray:
    """Landmarks (T, P, 2) float32 from any readable source (NaN rows kept), in their
    stored scheme or mapped to ``scheme`` (see :func:`load_sequence`)."""
    path = Path(path)
    meta_file = None
    if path.is_dir() and (path / "landmarks.npy").is_file():
        meta_file, path = path / "meta.json", path / "landmarks.npy"
    if path.suffix.lower() != ".npy":
        return load_sequence(path, scheme).landmarks
    arr = _np_load(path)
    meta = read_ingest_meta(meta_file.parent) if meta_file is not None else {}
    if meta_file is not None:  # an ingest folder: its landmarks must be the ones meta.json describes, as training's
        _check_ingest_pair(meta_file.parent, arr, meta)
    stored = stored_scheme(meta, arr, str(path))
    lm = validate_landmarks(arr, str(path), allow_nan_rows=True, scheme=stored)
    if scheme is None or scheme == stored:
        return lm
    return FaceSequence(lm, np.arange(len(lm)), name=str(path), scheme=stored).to_scheme(scheme).landmarks


def stored_scheme(meta: dict, landmarks: np.ndarray, where: str) -> str:
    """The scheme of stored landmarks: ``meta['landmarks']['scheme']`` when recorded (and
    consistent with the array), else the registered scheme with that many points."""
    rec = meta.get("landmarks", {}).get("scheme") if isinstance(meta.get("landmarks"), dict) else None
    shape = np.shape(landmarks)
    if rec is not None:
        get_scheme(rec).check(landmarks, where)
        return rec
    found = scheme_for_points(shape[-2]) if len(shape) >= 2 and shape[-1] == 2 else None
    if found is None:
        known = " or ".join(f"(N, {s.n_points}, 2) ({s.name})" for s in SCHEMES.values())
        raise FacesynthError(f"{where}: landmarks must have shape {known}, got {tuple(shape)}")
    return found.name


def save_landmarks(path: str | os.PathLike, landmarks: np.ndarray) -> None:
    """Write landmarks (T, 68, 2), choosing the writer by extension; atomic."""
    path = Path(path)
    key = "/" if (path.is_dir() or not path.suffix) else path.suffix.lower()
    if key not in WRITERS:
        raise FacesynthError(f"{path}: no landmark writer for '{key}' (writable: {', '.join(sorted(WRITERS))})")
    lm = np.asarray(landmarks)
    WRITERS[key](path, validate_landmarks(lm, str(path), allow_nan_rows=True, scheme=stored_scheme({}, lm, str(path))))


def _np_load(path: Path):
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FacesynthError(f"{path}: not a readable numpy file ({exc})") from None


@register_reader(".npy")
def _read_npy(path: Path) -> FaceSequence:
    lm = _np_load(path)
    return FaceSequence.from_arrays(lm, where=str(path), name=path.stem, meta={"source": str(path)},
                                    scheme=stored_scheme({}, lm, str(path)))


@register_reader(".npz")
def _read_npz(path: Path) -> FaceSequence:
    z = _np_load(path)
    if "landmarks" not in z.files:
        raise FacesynthError(f"{path}: .npz must hold an array named 'landmarks' (T, 68, 2); found {z.files}")
    frames = ArrayFrames(z["frames"]) if "frames" in z.files else None
    fps = float(z["fps"]) if "fps" in z.files else 30.0
    lm = z["landmarks"]
    return FaceSequence.from_arrays(lm, frames, where=str(path), name=path.stem, fps=fps, meta={"source": str(path)},
                                    scheme=stored_scheme({}, lm, str(path)))


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


def ingest_video(path: str | os.PathLike, meta: dict | None = None) -> tuple[Path | None, float | None]:
    """An ingest folder's video and frame rate, each None when absent: the video is
    ``meta.json``'s ``video.file`` (in the folder), else its ``video.path``, else
    ``video.mp4``; the rate is ``video.fps`` (0: unknown, as ingest records a video without
    one). ``meta``: the folder's meta.json, if already read (by :func:`read_ingest_meta`,
    which checks its fields: FacesynthError naming the file and field)."""
    path = Path(path)
    if meta is None:
        meta = read_ingest_meta(path)
    video = meta.get("video", {}) if isinstance(meta.get("video"), dict) else {}
    candidates = [path / str(video["file"])] if video.get("file") else []
    if video.get("path"):
        candidates.append(Path(str(video["path"])))
    candidates.append(path / "video.mp4")
    fps = video.get("fps")  # checked by read_ingest_meta: a number >= 0 or None
    return next((c for c in candidates if c.is_file()), None), float(fps) if fps else None


def _read_ingest_folder(path: Path) -> FaceSequence:
    meta = read_ingest_meta(path)
    video_path, video_fps = ingest_video(path, meta)
    video = meta.get("video", {}) if isinstance(meta.get("video"), dict) else {}
    frames = VideoFrames(video_path) if video_path is not None else None
    fps = float(video_fps or (frames.fps if frames else 30.0) or 30.0)
    meta = {**meta, "source": str(path)}
    if video_path is None:  # landmarks only; the video it should have, for the stages that need frames
        meta["missing_video"] = str(path / str(video["file"]) if video.get("file") else
                                    video.get("path") or path / "video.mp4")
    if video.get("sha256"):
        meta["source_sha256"] = video["sha256"]
    lm, where = _np_load(path / "landmarks.npy"), str(path / "landmarks.npy")
    _check_ingest_pair(path, lm, meta)
    info = meta.get("landmarks") if isinstance(meta.get("landmarks"), dict) else {}
    limited = isinstance(info.get("max_frames"), int) and len(lm) == info["max_frames"]  # ingest --max-frames N
    return FaceSequence.from_arrays(lm, frames, where=where, name=path.name, fps=fps, meta=meta,
                                    scheme=stored_scheme(meta, lm, where), first_rows_only=limited)


def _read_pts_folder(path: Path, pts: list[Path]) -> FaceSequence:
    images = []
    for p in pts:
        img = next((p.with_suffix(e) for e in IMAGE_EXTENSIONS if p.with_suffix(e).is_file()), None)
        if img is None:
            raise FacesynthError(f"{p}: no image with the same name ({'/'.join(IMAGE_EXTENSIONS)})")
        images.append(img)
    first = read_pts(pts[0], n_points=None)
    lm = np.stack([first] + [read_pts(p, n_points=len(first)) for p in pts[1:]])
    return FaceSequence.from_arrays(lm, ImageFiles(images), where=str(path), name=path.name, meta={"source": str(path)},
                                    scheme=stored_scheme({}, lm, str(path)))


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
