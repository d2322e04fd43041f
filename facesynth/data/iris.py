"""``ibug68+iris`` folders: dlib's 68 points with MediaPipe's iris points of the same frames.

Two routes, one writer (:func:`add_irises`):

* ``facesynth ingest VIDEO --out DIR --landmarker dlib+iris`` (:func:`ingest_dlib_iris`):
  ingests the video twice into a temporary folder, with dlib and with MediaPipe (Face Mesh
  with ``refine_landmarks``), then combines them;
* an existing dlib folder (e.g. a shipped clip of ``shared/data/faces``) plus a MediaPipe
  ingest of its video: ``add_irises(dlib_dir, mediapipe_dir, out_dir)``.

``landmarks.npy`` is float32 (T, 78, 2): rows 0-67 exactly as in the dlib folder, 68-77
MediaPipe's points 468-477 (right iris centre + 4 boundary points, then the left iris); a
row is NaN where either landmarker found no face. ``meta.json`` is the dlib folder's with
``landmarks.scheme = "ibug68+iris"`` and the iris source recorded; the video is referenced by
absolute path (or copied, when the dlib folder holds its copy).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from facesynth import __version__
from facesynth.data import detect, detect_mediapipe
from facesynth.data.ingest import check_output_folder, ingest_video
from facesynth.data.readers import array_sha256, load_sequence
from facesynth.data.sequence import FaceSequence
from facesynth.errors import FacesynthError
from facesynth.io import atomic_dir, read_json_object, write_json
from facesynth.landmarks import IBUG68, IBUG68_IRIS, MEDIAPIPE478

IRIS_SOURCE = MEDIAPIPE478.region("irises")  # 468-477, in the order of IBUG68_IRIS's 68-77


def combine_landmarks(dlib: np.ndarray, mediapipe: np.ndarray) -> np.ndarray:
    """dlib (T, 68, 2) and MediaPipe (T, 478, 2) landmarks of the same frames -> float32
    (T, 78, 2) ``ibug68+iris``; a row is NaN where either input row has a NaN."""
    dlib, mediapipe = np.asarray(dlib), np.asarray(mediapipe)
    IBUG68.check(dlib, "dlib landmarks")
    MEDIAPIPE478.check(mediapipe, "MediaPipe landmarks")
    if dlib.shape[:-2] != mediapipe.shape[:-2]:
        raise FacesynthError(f"dlib landmarks cover {dlib.shape[:-2]} frames, MediaPipe's {mediapipe.shape[:-2]}: "
                             "they must come from the same frames of the same video")
    out = np.concatenate([dlib, mediapipe[..., IRIS_SOURCE, :]], axis=-2).astype(np.float32)
    out[~np.isfinite(out).all(axis=(-1, -2))] = np.nan
    return out


def _raw_folder(path: Path, scheme: str) -> tuple[np.ndarray, dict]:
    """(T, P, 2) landmarks with their NaN rows, and meta.json, of an ingest-layout folder."""
    lm_path = path / "landmarks.npy"
    if not lm_path.is_file():
        raise FacesynthError(f"{path}: not a landmark folder (landmarks.npy missing)")
    meta = read_json_object(path / "meta.json") if (path / "meta.json").is_file() else {}
    recorded = (meta.get("landmarks") or {}).get("scheme")
    lm = np.load(lm_path)
    n_points = (IBUG68 if scheme == IBUG68.name else MEDIAPIPE478).n_points
    if recorded not in (None, scheme) or lm.ndim != 3 or lm.shape[1:] != (n_points, 2):
        raise FacesynthError(f"{lm_path}: expected {scheme} landmarks, got shape {lm.shape}"
                             + (f" (scheme {recorded})" if recorded else ""))
    return lm, meta


def add_irises(dlib_dir: str | os.PathLike, mediapipe_dir: str | os.PathLike, out_dir: str | os.PathLike) -> FaceSequence:
    """Write ``out_dir`` (``ibug68+iris``) from a dlib folder and a MediaPipe folder of the
    same video (frame t of one is frame t of the other); returns it read back."""
    dlib_dir, mp_dir, out_dir = Path(dlib_dir), Path(mediapipe_dir), Path(out_dir)
    lm68, meta = _raw_folder(dlib_dir, "ibug68")
    lm478, mp_meta = _raw_folder(mp_dir, "mediapipe478")
    if len(lm68) != len(lm478):
        raise FacesynthError(f"{dlib_dir} has {len(lm68)} frames, {mp_dir} {len(lm478)}: not the same video")
    sha = [((m.get("video") or {}).get("sha256")) for m in (meta, mp_meta)]
    if None not in sha and sha[0] != sha[1]:
        raise FacesynthError(f"{dlib_dir} and {mp_dir} were ingested from different videos (video SHA-256 differs)")
    lm = combine_landmarks(lm68, lm478)
    video = dict(meta.get("video") or {})
    for cand in ([dlib_dir / video["file"]] if video.get("file") else []) + [dlib_dir / "video.mp4"]:
        if cand.is_file():  # reference the dlib folder's copy by absolute path
            video.pop("file", None)
            video["path"] = str(cand.resolve())
            break
    missing = np.flatnonzero(~np.isfinite(lm).all(axis=(1, 2)))
    out_meta = {
        **meta,
        "name": out_dir.name,
        "video": video,
        "landmarks": {
            **(meta.get("landmarks") or {}),
            "shape": list(lm.shape),
            "dtype": "float32",
            "scheme": IBUG68_IRIS.name,
            "markup": IBUG68_IRIS.description,
            "landmarker": "dlib+iris",
            "sha256": array_sha256(lm),
            "irises": {"from": str(mp_dir.resolve()), "points": "MediaPipe Face Mesh 468-477 (refine_landmarks)",
                       "detector": (mp_meta.get("landmarks") or {}).get("detector"),
                       "detector_versions": mp_meta.get("detector_versions")},
            "points_0_67_from": str(dlib_dir.resolve()),
            "frames_without_both": [int(i) for i in missing],
        },
        "facesynth_version": __version__,
        "created_by": "facesynth add_irises",
    }
    with atomic_dir(out_dir) as tmp:
        with open(tmp / "landmarks.npy", "wb") as f:
            np.save(f, lm)
        write_json(tmp / "meta.json", out_meta)
    return load_sequence(out_dir)


def ingest_dlib_iris(video_path: str | os.PathLike, out_dir: str | os.PathLike, **kwargs) -> FaceSequence:
    """``ingest_video`` with dlib and with MediaPipe, combined by :func:`add_irises`
    (keyword arguments as :func:`facesynth.data.ingest.ingest_video`, except ``landmarker``
    and ``detector``); needs both the ``ingest`` and the ``mediapipe`` extras."""
    out_dir = Path(out_dir)
    if kwargs.get("copy") or kwargs.get("export_pts"):
        raise FacesynthError("--copy and --export-pts are not available with --landmarker dlib+iris "
                             "(the folder references the video by path; .pts files hold 68 points)")
    check_output_folder(out_dir, [video_path])
    detect.check_extra()
    detect_mediapipe.check_extra()
    with tempfile.TemporaryDirectory(prefix="facesynth-iris-") as tmp:
        ingest_video(video_path, Path(tmp) / "dlib", landmarker="dlib", **kwargs)
        kwargs = {k: v for k, v in kwargs.items() if k not in ("max_side", "reuse_limit")}  # dlib-only settings
        ingest_video(video_path, Path(tmp) / "mediapipe", landmarker="mediapipe", **kwargs)
        return add_irises(Path(tmp) / "dlib", Path(tmp) / "mediapipe", out_dir)
