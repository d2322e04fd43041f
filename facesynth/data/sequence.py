"""``FaceSequence``: the frames and landmarks of one subject, in one landmark scheme
(``ibug68`` by default, or ``mediapipe478``; see facesynth/landmarks.py)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import numpy as np

from facesynth.data.frames import FrameSource
from facesynth.errors import FacesynthError
from facesynth.landmarks import DEFAULT_SCHEME, get_scheme
from facesynth.provenance import array_fingerprint

log = logging.getLogger(__name__)



def validate_landmarks(landmarks: np.ndarray, where: str, allow_nan_rows: bool = False, scheme: str = DEFAULT_SCHEME.name) -> np.ndarray:
    """Check and convert landmarks to float32 (N, P, 2), P the point count of ``scheme``.

    Parameters
    ----------
    landmarks : array-like
        (N, P, 2) or a single (P, 2) frame, (x, y) pixels.
    where : str
        File or field name used in error messages.
    allow_nan_rows : bool
        Whether whole-frame NaN rows (frames without a face) are allowed.
    scheme : str
        Landmark scheme name (``ibug68``: the 68-point stages' only input). Landmarks of
        another scheme are an error that says how to map them.
    """
    lm = np.asarray(landmarks)
    if lm.ndim == 2:
        lm = lm[None]
    sch = get_scheme(scheme)
    if lm.ndim != 3 or lm.shape[1:] != (sch.n_points, 2):
        raise FacesynthError(f"{where}: landmarks must have shape (N, {sch.n_points}, 2) ({sch.description}), "
                             f"got {lm.shape}{sch.mismatch_hint(lm.shape)}")
    if lm.dtype.kind not in "fiu":  # complex ones too: their imaginary part would be dropped
        raise FacesynthError(f"{where}: landmarks must be real numbers, got dtype {lm.dtype}")
    lm = lm.astype(np.float32, copy=False)
    bad = ~np.isfinite(lm)
    if bad.any():
        rows = bad.any(axis=(1, 2))
        partial = rows & ~bad.all(axis=(1, 2))
        if partial.any() or not allow_nan_rows:
            first = int(np.flatnonzero(partial if partial.any() else rows)[0])
            raise FacesynthError(
                f"{where}: landmarks of frame {first} contain NaN/inf"
                + (" in some points only (a frame is either all NaN or all finite)" if partial.any() else "")
            )
    return lm


FRAME_MARGIN = 0.25  # training landmarks may stray this fraction of the frame size outside it (faces at the border)


def check_landmarks_in_frame(landmarks: np.ndarray, size: tuple[int, int], where: str, margin: float = FRAME_MARGIN) -> None:
    """FacesynthError naming the rows of (N, P, 2) landmarks (NaN rows skipped) with a point
    outside the frame of ``size`` (W, H) by more than ``margin`` of its size: wrong units, a
    scale or an offset, or another video's landmarks, caught before any frame is decoded.
    Training data is held to :data:`FRAME_MARGIN`; a driver of ``facesynth app`` to one whole
    frame size (``margin=1``: a head may leave the frame, its landmarks not another video's)."""
    w, h = size
    lo = -margin * np.array([w, h], np.float32)
    hi = (1 + margin) * np.array([w, h], np.float32)
    with np.errstate(invalid="ignore"):
        out = ((landmarks < lo) | (landmarks > hi)).any(axis=(1, 2))
    if out.any():
        rows = np.flatnonzero(out)
        raise FacesynthError(
            f"{where}: landmarks of {len(rows)} of {len(landmarks)} rows (first {rows[:10].tolist()}) lie outside the "
            f"{w}x{h} frame by more than {margin:.0%} of its size (wrong units or offset, or another video's landmarks?)")


MIN_FACE_PX = 8.0  # a face whose landmarks span less than this (wider side of their box) is no face


def check_face_size(landmarks: np.ndarray, where: str, min_px: float = MIN_FACE_PX) -> None:
    """FacesynthError naming the rows of (N, P, 2) landmarks (NaN rows skipped) whose box is
    smaller than ``min_px`` on its wider side: landmarks in 0-1 units instead of pixels, or
    collapsed to one point, caught before any model is fitted on them."""
    with np.errstate(invalid="ignore"):
        span = np.nanmax(np.ptp(landmarks, axis=1), axis=1) if len(landmarks) else np.zeros(0)
    small = np.flatnonzero(span < min_px)
    if len(small):
        raise FacesynthError(
            f"{where}: landmarks of {len(small)} of {len(landmarks)} rows (first {small[:10].tolist()}) span "
            f"{float(span[small[0]]):.3g} px, a face needs at least {min_px:g} px (landmarks in 0-1 units instead "
            "of pixels, or collapsed to one point?)")


@dataclass
class FaceSequence:
    """One subject's frames and landmarks.

    Attributes
    ----------
    landmarks : np.ndarray
        float32 (N, P, 2), (x, y) pixels, 0-based, in the order of ``scheme`` (P = 68 for
        ``ibug68``, 478 for ``mediapipe478``); never NaN (frames without a face are dropped
        on loading and counted in ``meta['dropped_frames']``).
    frame_index : np.ndarray
        int64 (N,): each row's frame number in ``frames`` (the original video).
    frames : FrameSource or None
        Where images come from; ``None`` for landmark-only sequences.
    fps : float
    name : str
    meta : dict
        Free-form provenance (source file, detector, ...).
    scheme : str
        Landmark scheme name (facesynth/landmarks.py ``SCHEMES``).
    tracked : np.ndarray or None
        The landmarks as tracked when ``landmarks`` were smoothed (``data.smooth_landmarks``,
        :mod:`facesynth.data.smoothing`), same shape; ``None`` otherwise.
    """

    landmarks: np.ndarray
    frame_index: np.ndarray
    frames: FrameSource | None = None
    fps: float = 30.0
    name: str = "sequence"
    meta: dict = field(default_factory=dict)
    scheme: str = DEFAULT_SCHEME.name
    tracked: np.ndarray | None = None

    @classmethod
    def from_arrays(
        cls,
        landmarks: np.ndarray,
        frames: FrameSource | None = None,
        *,
        where: str = "landmarks",
        first_rows_only: bool = False,
        **kwargs,
    ) -> "FaceSequence":
        """Validate landmarks (T, P, 2) of ``scheme`` (keyword, default ``ibug68``), drop NaN
        frames (logged), and build a sequence. Fewer landmark rows than frames is warned
        about unless ``first_rows_only`` (the landmarks cover the first frames on purpose,
        e.g. an ingest limited by ``max_frames``)."""
        lm = validate_landmarks(landmarks, where, allow_nan_rows=True, scheme=kwargs.get("scheme", DEFAULT_SCHEME.name))
        if frames is not None and len(frames) and len(frames) < len(lm):
            raise FacesynthError(f"{where}: {len(lm)} landmark frames but only {len(frames)} image frames")
        if frames is not None and len(frames) and len(lm) < len(frames) and not first_rows_only:
            log.warning("%s: %d landmark rows for %d video frames: row t is paired with frame t, the last %d frames "
                        "are unused (landmarks of a shorter clip?)", where, len(lm), len(frames), len(frames) - len(lm))
        if frames is not None and all(int(v) > 0 for v in frames.size):
            check_landmarks_in_frame(lm, tuple(frames.size)[::-1], where)  # frames.size is (H, W)
        keep = np.isfinite(lm).all(axis=(1, 2))
        meta = dict(kwargs.pop("meta", {}) or {})
        dropped = int((~keep).sum())
        meta["dropped_frames"] = dropped
        if dropped:
            log.info("%s: dropped %d of %d frames without landmarks (NaN rows)", where, dropped, len(lm))
        if not keep.any():
            raise FacesynthError(f"{where}: no frame has landmarks (all {len(lm)} rows are NaN)")
        return cls(landmarks=lm[keep], frame_index=np.flatnonzero(keep).astype(np.int64), frames=frames, meta=meta, **kwargs)

    def __len__(self) -> int:
        return len(self.landmarks)

    @property
    def has_frames(self) -> bool:
        return self.frames is not None

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        if self.frames is None:
            raise FacesynthError(f"{self.name}: sequence has landmarks only, no frames")
        return tuple(self.frames.size)

    @property
    def fingerprint(self) -> str:
        """Hash of the landmarks as loaded (``tracked``, when smoothed: the data, whose smoothing
        the run's config records) and frame numbers (and source file hash, when known)."""
        extra = np.frombuffer(str(self.meta.get("source_sha256", "")).encode(), dtype=np.uint8)
        return array_fingerprint(self.as_tracked, self.frame_index, extra)

    def iter_frames(self, rows: Sequence[int] | None = None) -> Iterator[np.ndarray]:
        """Yield uint8 RGB (H, W, 3) images for sequence rows (default: all), in order."""
        if self.frames is None:
            raise FacesynthError(f"{self.name}: sequence has landmarks only, no frames")
        rows = np.arange(len(self)) if rows is None else np.asarray(rows)
        yield from self.frames.read(self.frame_index[rows])

    def frame(self, row: int) -> np.ndarray:
        """uint8 RGB (H, W, 3) image of one row."""
        return next(self.iter_frames([row]))

    def load_frames(self, rows: Sequence[int] | None = None) -> np.ndarray:
        """uint8 (n, H, W, 3) images of ``rows``. Mind memory: 1000 frames at 512x512 take 786 MB."""
        return np.stack(list(self.iter_frames(rows)))

    def subset(self, rows: Sequence[int]) -> "FaceSequence":
        """A sequence of the given rows (frames stay lazily referenced)."""
        rows = np.asarray(rows)
        return FaceSequence(self.landmarks[rows], self.frame_index[rows], self.frames, self.fps, self.name, dict(self.meta),
                            self.scheme, self._tracked(lambda t: t[rows]))

    @property
    def as_tracked(self) -> np.ndarray:
        """The landmarks as the tracker gave them: ``tracked`` when smoothed, else ``landmarks``."""
        return self.landmarks if self.tracked is None else self.tracked

    def _tracked(self, change):
        """``change`` applied to the tracked landmarks too, when the sequence keeps them."""
        return None if self.tracked is None else change(self.tracked)

    def require_scheme(self, scheme: str, stage: str) -> None:
        """FacesynthError unless the landmarks are in ``scheme`` (for stages that take one scheme
        only), naming the mapping when there is one."""
        if self.scheme == scheme:
            return
        how = (f": map it with seq.to_scheme('{scheme}') or load_sequence(path, scheme='{scheme}')"
               if scheme == "ibug68" and get_scheme(self.scheme).ibug68 is not None else "")
        raise FacesynthError(f"{self.name}: {stage} takes {scheme} landmarks, this sequence has {self.scheme}{how}")

    def to_scheme(self, scheme: str) -> "FaceSequence":
        """This sequence with its landmarks in ``scheme``: itself when already there; mapped
        when a mapping exists (today: any scheme -> ``ibug68``, approximate, see
        docs/landmarks.md); FacesynthError otherwise."""
        if scheme == self.scheme:
            return self
        target, source = get_scheme(scheme), get_scheme(self.scheme)
        if source.base == target.name:  # exact: the first points are the base scheme's (ibug68+iris -> ibug68)
            meta = {**self.meta, "mapped_from_scheme": self.scheme}
            return FaceSequence(np.ascontiguousarray(self.landmarks[:, : target.n_points]), self.frame_index,
                                self.frames, self.fps, self.name, meta, scheme,
                                self._tracked(lambda t: np.ascontiguousarray(t[:, : target.n_points])))
        if target.name != "ibug68" or source.ibug68 is None:
            raise FacesynthError(f"{self.name}: {self.scheme} landmarks cannot be mapped to {scheme} "
                                 "(only mappings to ibug68 exist)")
        log.info("%s: %s landmarks mapped to ibug68 (approximate, see docs/landmarks.md)", self.name, self.scheme)
        meta = {**self.meta, "mapped_from_scheme": self.scheme}
        return FaceSequence(source.to_ibug68(self.landmarks), self.frame_index, self.frames, self.fps, self.name, meta, scheme,
                            self._tracked(source.to_ibug68))
