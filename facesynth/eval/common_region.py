"""The frame region that both landmark schemes are judged on (``psnr_frame_common`` of
``metrics.json``).

Two face models on different schemes have different reference frames and face masks, so
their ``psnr_ref`` and ``psnr_frame`` are not comparable. ``psnr_frame_common`` measures
both over the same pixels of each test frame: the convex hull of the clip's **dlib**
landmarks 0-26 (jaw and brows; the shipped ``landmarks.npy`` of ``shared/data/faces/<clip>``)
eroded by 3 px (``whole``), with per-region figures inside it: the parts of
:func:`facesynth.landmarks.face_region_masks` (``eyes``, ``mouth_interior``, ``lips``,
``brows``, ``rest``), the same definition SADM's per-region shrinkage and the ceiling study
use in the reference frame, cut to the common region.

Where the dlib landmarks come from (:func:`common_landmarks`): ``eval.common_landmarks``
when set (a ``.npy`` (T, 68, 2) indexed by video frame, or a clip folder holding one);
otherwise an ``ibug68`` sequence that was not mapped from another scheme uses its own
landmarks (as tracked, when ``data.smooth_landmarks`` smoothed them: the judged pixels do not
depend on the smoothing), and any other sequence the ``landmarks.npy`` beside the source video that its
``meta.json`` records (``video.path``, as ``facesynth ingest`` writes it), when that holds
68 points per frame of the video. Anything else is a FacesynthError naming the setting.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facesynth.data.readers import load_landmarks
from facesynth.errors import FacesynthError
from facesynth.landmarks import BROWS, FACE_REGIONS, JAW, face_region_masks

HULL_POINTS = JAW + BROWS  # dlib 0-26
ERODE_PX = 3
REGIONS = ("whole",) + FACE_REGIONS


def common_landmarks(seq, path: str | None = None) -> np.ndarray:
    """float32 (len(seq), 68, 2): the dlib landmarks of each row's video frame (see the module
    docstring for where they come from); FacesynthError when there are none."""
    if path:
        source = Path(path)
        lm = _load68(source, "eval.common_landmarks")
    elif seq.scheme == "ibug68" and "mapped_from_scheme" not in seq.meta:
        return np.asarray(seq.as_tracked, np.float32)
    else:
        video = seq.meta.get("video", {}) if isinstance(seq.meta.get("video"), dict) else {}
        source = Path(video["path"]).parent / "landmarks.npy" if video.get("path") else None
        if source is None or not source.is_file():
            raise FacesynthError(
                f"{seq.name}: psnr_frame_common needs the clip's dlib 68 landmarks and this {seq.scheme} sequence "
                f"records none beside its video ({source or 'no video.path in meta.json'}): set "
                "eval.common_landmarks=PATH (a (T, 68, 2) .npy or a clip folder) or eval.common_region=false")
        lm = _load68(source, f"{seq.name}: the landmarks beside the source video")
    if len(lm) <= int(np.max(seq.frame_index)):
        raise FacesynthError(f"{source}: {len(lm)} frames of common landmarks, but {seq.name} uses video frame "
                             f"{int(np.max(seq.frame_index))}")
    out = lm[seq.frame_index]
    if not np.isfinite(out).all():
        raise FacesynthError(f"{source}: no common landmarks (NaN) for some frames of {seq.name}")
    return out


def _load68(path: Path, what: str) -> np.ndarray:
    lm = load_landmarks(path)
    if lm.shape[1:] != (68, 2):
        raise FacesynthError(f"{path}: {what} must be dlib's 68 points (T, 68, 2), got {lm.shape}")
    return lm


def region_masks(landmarks68: np.ndarray, box: tuple[int, int, int, int]) -> dict[str, np.ndarray]:
    """bool (y1 - y0, x1 - x0) masks of :data:`REGIONS` for one frame's (68, 2) dlib
    landmarks, in the frame box ``(y0, y1, x0, x1)``. Polygons are filled at pixel centres
    (sub-pixel vertices, 4 fractional bits); the hull is eroded by a disc of radius 3 px and
    the parts (:func:`facesynth.landmarks.face_region_masks`) partition it."""
    y0, y1, x0, x1 = box
    shape = (y1 - y0, x1 - x0)
    pts = np.asarray(landmarks68, np.float64) - (x0, y0)
    hull = np.zeros(shape, np.uint8)
    cv2.fillPoly(hull, [cv2.convexHull(np.round(pts[list(HULL_POINTS)] * 16).astype(np.int32))], 1, cv2.LINE_8, shift=4)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ERODE_PX + 1, 2 * ERODE_PX + 1))
    whole = cv2.erode(hull, disc) > 0
    return {"whole": whole, **face_region_masks(pts, shape, within=whole)}


def hull_box(landmarks68: np.ndarray, frame_hw: tuple[int, int], margin: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the frame box around dlib points 0-26 plus ``margin``, clipped."""
    p = np.asarray(landmarks68, np.float64)[list(HULL_POINTS)]
    x0, y0 = np.floor(p.min(0)).astype(int) - margin
    x1, y1 = np.ceil(p.max(0)).astype(int) + 1 + margin
    return max(y0, 0), min(y1, frame_hw[0]), max(x0, 0), min(x1, frame_hw[1])
