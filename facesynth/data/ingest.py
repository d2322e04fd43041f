"""Video ingest: a real video becomes a training folder (``landmarks.npy`` + ``meta.json``).

The folder has the layout of ``shared/data/faces/<clip>`` and is read back by
:func:`facesynth.data.load_sequence`:

* ``landmarks.npy``: float32 (T, P, 2), (x, y) 0-based pixels of the decoded frame, in
  the landmarker's scheme (dlib: ``ibug68``, P = 68; MediaPipe: ``mediapipe478``,
  P = 478), NaN rows where no face was found (or the frame was skipped by ``every``);
  row t is frame t of the video (OpenCV decode order);
* ``meta.json``: the video (path or copied file, resolution, fps, frame count,
  SHA-256), the landmark array description, its scheme (``landmarks.scheme``, read back
  by the loader) and landmarker, statistics (detection rate, how each frame's face was
  found, timing), landmarker and package versions;
* optionally ``video.mp4`` (a copy, ``copy=True``) and ``pts/<frame>.pts`` (one iBUG
  ``.pts`` file per frame with a face, 1-based coordinates as the format requires).

Detection and landmarks: ``landmarker="dlib"`` (default), :mod:`facesynth.data.detect`
(dlib HOG + 68-point shape predictor, the optional ``ingest`` extra); or
``landmarker="mediapipe"``, :mod:`facesynth.data.detect_mediapipe` (Face Mesh with irises,
478 points, tracking between frames; the optional ``mediapipe`` extra). dlib stays the
default: docs/landmarks.md gives the measurements behind that choice. Every file is
written atomically and only after all frames are processed; ``meta.json`` is written last.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from facesynth import __version__
from facesynth.data import detect_mediapipe
from facesynth.data.detect import Detections, LandmarkDetector, check_extra, detect_landmarks, detector_versions
from facesynth.data.pts import write_pts
from facesynth.data.readers import array_sha256, load_sequence
from facesynth.data.sequence import FaceSequence
from facesynth.errors import FacesynthError
from facesynth.io import atomic_dir, check_writable, refuse_overwriting_inputs, write_json
from facesynth.landmarks import LandmarkScheme, get_scheme
from facesynth.progress import bar as progress_bar
from facesynth.progress import note
from facesynth.provenance import file_sha256, package_versions

log = logging.getLogger(__name__)

LANDMARKERS = {"dlib": "ibug68", "mediapipe": "mediapipe478"}
"""Landmarker name -> the scheme it writes."""
PRECISION = {
    "dlib": "integer-valued: dlib shape_predictor returns integer pixel coordinates",
    "mediapipe": "sub-pixel: MediaPipe's normalised coordinates * size - 0.5",
}


class _Video:
    """An opened video: header facts plus a forward frame iterator with decode timing."""

    def __init__(self, path: Path):
        self.path = path
        if not path.is_file():
            raise FacesynthError(f"{path}: video file not found")
        cap = cv2.VideoCapture(str(path))
        ok, first = cap.read() if cap.isOpened() else (False, None)
        if not ok or first is None:
            cap.release()
            raise FacesynthError(f"{path}: unreadable video (OpenCV could not decode a frame)")
        self.height, self.width = first.shape[:2]
        self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.header_frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        cap.release()
        self.decoded = 0
        self.decode_s = 0.0
        self.reached_end = False

    def frames(self, every: int, max_frames: int | None) -> Iterator[np.ndarray | None]:
        """Yield RGB frames (``None`` for frames skipped by ``every``), at most ``max_frames``."""
        cap = cv2.VideoCapture(str(self.path))
        try:
            i = 0
            while max_frames is None or i < max_frames:
                t0 = time.perf_counter()
                if i % every == 0:
                    ok, bgr = cap.read()
                    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB) if ok else None
                else:
                    ok, rgb = cap.grab(), None
                self.decode_s += time.perf_counter() - t0
                if not ok:
                    self.reached_end = True
                    return
                self.decoded += 1
                yield rgb
                i += 1
        finally:
            cap.release()


def check_output_folder(out_dir: Path, inputs=()) -> None:
    """An ingest output folder can be written: not a file, its parent writable, not one of
    ``inputs`` nor a folder holding one (e.g. the video copied into an earlier ingest
    folder), and, when it exists and holds files, an earlier ingest folder (which is
    replaced as a whole)."""
    check_writable(out_dir, folder=True)
    refuse_overwriting_inputs([out_dir], inputs)
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / "meta.json").is_file():
        raise FacesynthError(f"{out_dir}: output folder exists and is not an ingest folder (no meta.json); "
                             "it would be replaced as a whole: choose a new or empty folder")


def _progress(total: int | None, enabled: bool):
    return progress_bar(total=total, unit="frame", desc="ingest", enabled=enabled)


def _stats(det: Detections, video: _Video, wall_s: float, scheme: LandmarkScheme) -> dict:
    n_proc = det.n_processed
    counts = det.counts()
    lm = det.landmarks
    ok = np.isfinite(lm[:, 0, 0])
    stats = {
        "frames_processed": n_proc,
        "detection_rate": round(det.detection_rate, 6),
        "det_source_counts": counts,
        "frames_with_multiple_faces": int((det.n_faces > 1).sum()),
        "timing_ms_per_frame": {
            "decode": 1000 * video.decode_s / max(video.decoded, 1),
            "detect": 1000 * det.timing_s["detect"] / max(n_proc, 1),
            "landmarks": 1000 * det.timing_s["landmarks"] / max(n_proc, 1),
        },
        "wall_s": wall_s,
        "frames_per_s": n_proc / wall_s if wall_s > 0 else None,
    }
    if ok.any():
        corners = scheme.region("eye_corners")  # outer corners first and last
        iod = np.linalg.norm(lm[ok, corners[-1]] - lm[ok, corners[0]], axis=1)
        stats["iod_px"] = {"p5": float(np.percentile(iod, 5)), "p50": float(np.median(iod)), "p95": float(np.percentile(iod, 95))}
    return stats


def ingest_video(
    video_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    every: int = 1,
    max_frames: int | None = None,
    copy: bool = False,
    export_pts: bool = False,
    progress: bool = False,
    detector: LandmarkDetector | detect_mediapipe.MediaPipeLandmarker | None = None,
    max_side: int = 640,
    reuse_limit: int = 15,
    landmarker: str = "dlib",
) -> FaceSequence:
    """Detect the face and fit landmarks in every frame of a video; write a training folder.

    Parameters
    ----------
    video_path : path-like
        Any video OpenCV decodes.
    out_dir : path-like
        Output folder (created; files written atomically once all frames are done).
    every : int
        Process every ``every``-th frame; the others get NaN rows (and are dropped on loading).
    max_frames : int, optional
        Only the first ``max_frames`` frames of the video (``landmarks.npy`` has that many rows).
    copy : bool
        Copy the video into ``out_dir/video<ext>`` (``meta['video']['file']``) instead of
        referencing its absolute path (``meta['video']['path']``).
    export_pts : bool
        Also write ``out_dir/pts/<frame>.pts`` for each frame with a face (1-based coordinates).
    progress : bool
        Show a tqdm progress bar (frames/s).
    detector : LandmarkDetector or MediaPipeLandmarker, optional
        A loaded landmarker of kind ``landmarker`` to reuse (it is reset first); by default
        one is made (dlib: with ``max_side`` and ``reuse_limit``; MediaPipe: video mode).
    max_side, reuse_limit : int
        See :class:`facesynth.data.detect.LandmarkDetector` (dlib only).
    landmarker : str
        ``"dlib"`` (68 iBUG points, the ``ingest`` extra) or ``"mediapipe"`` (478 points
        with irises, the ``mediapipe`` extra).

    Returns
    -------
    FaceSequence
        The written folder read back with :func:`facesynth.data.load_sequence` (frames
        decoded lazily from the video; NaN frames dropped).

    Raises
    ------
    FacesynthError
        Unreadable video, no face in any processed frame, bad arguments.
    MissingExtraError
        dlib or face_recognition_models is not installed (``pip install 'facesynth[ingest]'``),
        or MediaPipe (see :mod:`facesynth.data.detect_mediapipe`).
    """
    video_path, out_dir = Path(video_path), Path(out_dir)
    if landmarker not in LANDMARKERS:
        raise FacesynthError(f"landmarker must be one of {', '.join(LANDMARKERS)}, got {landmarker!r}")
    scheme = get_scheme(LANDMARKERS[landmarker])
    if every < 1:
        raise FacesynthError(f"every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise FacesynthError(f"max_frames must be >= 1, got {max_frames}")
    check_output_folder(out_dir, [video_path])  # before any frame is decoded
    if detector is None:  # a missing extra is reported before anything else
        (check_extra if landmarker == "dlib" else detect_mediapipe.check_extra)()
    video = _Video(video_path)
    det, detect, versions = _landmarker(landmarker, detector, max_side, reuse_limit)
    result, wall = _detect_all(video, det, detect, every, max_frames, progress, landmarker)
    stats = _stats(result, video, wall, scheme)
    meta = {**_meta(video, result, det, scheme, landmarker, stats, out_dir, every=every, max_frames=max_frames,
                    copy=copy, export_pts=export_pts),
            "detector_versions": versions(), "versions": package_versions(), "facesynth_version": __version__,
            "created_by": "facesynth ingest"}
    _write_folder(out_dir, video_path, result.landmarks, meta, copy, export_pts)
    log.debug(  # debug: the command prints the summary itself (once)
        "%s: %d frames processed in %.1f s (%.1f frames/s), detection rate %.3f -> %s",
        video_path, result.n_processed, wall, stats["frames_per_s"] or 0.0, stats["detection_rate"], out_dir,
    )
    return load_sequence(out_dir)


def _landmarker(landmarker: str, detector, max_side: int, reuse_limit: int):
    """(landmarker reset for a new video, its detect function, its versions function)."""
    if landmarker == "dlib":
        det = detector or LandmarkDetector(max_side=max_side, reuse_limit=reuse_limit)
        detect, versions = detect_landmarks, detector_versions
    else:
        det = detector or detect_mediapipe.MediaPipeLandmarker()
        detect, versions = detect_mediapipe.detect_landmarks_mediapipe, detect_mediapipe.mediapipe_versions
    det.reset()
    return det, detect, versions


def _detect_all(video: _Video, det, detect, every: int, max_frames: int | None, progress: bool,
                landmarker: str) -> tuple[Detections, float]:
    """Landmarks of every processed frame with a progress bar; (detections, wall seconds).
    No face in any frame is a FacesynthError."""
    total = video.header_frames or None
    if max_frames is not None:
        total = min(total, max_frames) if total else max_frames
    if progress:
        note(f"ingest: {video.path} ({video.width}x{video.height}, {total or '?'} frames) with {landmarker}")
    t0 = time.perf_counter()
    with _progress(total, progress) as bar:
        def on_frame(i: int, source: str) -> None:
            bar.update(i + 1 - bar.n)

        result = detect(video.frames(every, max_frames), det, on_frame=on_frame)
        bar.update(video.decoded - bar.n)
    wall = time.perf_counter() - t0
    n_found = int(np.isfinite(result.landmarks[:, 0, 0]).sum())
    if n_found == 0:
        raise FacesynthError(f"{video.path}: no face found in any of the {result.n_processed} frames processed")
    return result, wall


def _meta(video: _Video, result: Detections, det, scheme: LandmarkScheme, landmarker: str, stats: dict, out_dir: Path,
          *, every: int, max_frames: int | None, copy: bool, export_pts: bool) -> dict:
    """meta.json of an ingest folder (without the package versions), the landmarks' SHA-256 included."""
    video_path = video.path
    n_video = video.decoded if video.reached_end else max(video.header_frames, video.decoded)
    vmeta = {
        "width": video.width, "height": video.height, "fps": video.fps, "frames": n_video,
        "duration_s": n_video / video.fps if video.fps else None, "sha256": file_sha256(video_path),
    }
    src_abs = video_path.resolve()
    if copy:
        vmeta["file"] = "video" + (video_path.suffix.lower() or ".mp4")
        vmeta["original_path"] = str(src_abs)
    else:
        vmeta["path"] = str(src_abs)
    meta = {
        "name": out_dir.name,
        "source": {"path": str(src_abs)},
        "video": vmeta,
        "landmarks": {
            "file": "landmarks.npy",
            "shape": list(result.landmarks.shape),
            "dtype": "float32",
            "scheme": scheme.name,
            "markup": scheme.description,
            "coords": "x,y in pixels of the original frame (OpenCV decode order)",
            "missing": "NaN rows (no face" + (f", or skipped: only every {every}th frame processed)" if every > 1 else ")"),
            "precision": PRECISION[landmarker],
            "landmarker": landmarker,
            "detector": det.describe(),
            "every": every,
            "max_frames": max_frames,
            "pts_dir": "pts" if export_pts else None,
            "frames_missed" if landmarker == "mediapipe" else "frames_not_hog_up0":
                [i for i, s in enumerate(result.sources) if s not in (result.source_names[0], "skipped")],
        },
        "stats": stats,
    }
    meta["landmarks"]["sha256"] = array_sha256(result.landmarks)
    return meta


def _write_folder(out_dir: Path, video_path: Path, landmarks: np.ndarray, meta: dict, copy: bool, export_pts: bool) -> None:
    """Write the folder into a temporary sibling, which then replaces ``out_dir`` as a whole
    (io.atomic_dir): the folder is complete or absent, never a mix."""
    with atomic_dir(out_dir) as tmp_dir:
        if copy:
            shutil.copyfile(video_path, tmp_dir / meta["video"]["file"])
        with open(tmp_dir / "landmarks.npy", "wb") as f:
            np.save(f, landmarks)
        if export_pts:
            width = max(6, len(str(len(landmarks))))
            for i, frame in enumerate(landmarks):
                if np.isfinite(frame).all():
                    write_pts(tmp_dir / "pts" / f"{i:0{width}d}.pts", frame)
        write_json(tmp_dir / "meta.json", meta)
