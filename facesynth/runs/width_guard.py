"""A reference width guarded on validation PSNR (``model.width_guard``).

A wider reference frame (``model.reference_width=auto``: the faces' width in the video, up to
256 px) keeps detail that the 128 px default blurs, but on some clips it renders the held-out
frames a few tenths of a dB lower. With ``model.width_guard=G`` (dB) the training app scores
each candidate width (:func:`candidate_widths`: 128, the one asked for, and one half-way
between when there is room) on validation slices as the restoration filter's guard builds its
one (:func:`facesynth.model.restore.validation_predictions`): the face model and the mapping
fitted on the training rows before a slice and a gap as long
(:func:`facesynth.sadm.fit.held_out_predictions`), the slice's predictions pasted into their
real frames and scored over the common region (:func:`facesynth.eval.frame_level.psnr_common`,
what ``psnr_frame_common`` measures on the test frames). The slices are the last
blocks of the validation's length (:func:`facesynth.model.restore.slice_stops`, the filter's
guard's too): one slice misjudges
clips whose cost changes along the video (vrt_face5: 0.43 dB better at 256 px on the last
slice, 0.66 dB worse on the test frames, 0.57 dB worse on the earliest slice;
``bench/studies/width_guard.py``). It keeps the widest width whose PSNR is at most ``G`` below
128's on every slice (:func:`choose_width`) and fits the face model at that width on every
training row. The restoration filter is off while the widths are scored (its own guard is
``sadm.restore_guard``). The choice and the figures are recorded in ``metrics.json``
(``width_guard``) and in the face model's meta.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.eval.frame_level import psnr_common
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.reference import AUTO_WIDTH, reference_width
from facesynth.model.restore import fit_size, slice_stops
from facesynth.sadm.fit import SADMConfig, held_out_predictions, resolve_sadm_config, validation_size

log = logging.getLogger(__name__)
BASE_WIDTH = AUTO_WIDTH[0]  # the width every candidate's PSNR is compared with (today's default)


def check_width_guard(value) -> float | None:
    """``model.width_guard`` as a float (dB, >= 0), or None (off); FacesynthError naming the field otherwise."""
    if value is None:
        return None
    try:
        guard = float(value)
    except (TypeError, ValueError):
        guard = math.nan
    if isinstance(value, bool) or not math.isfinite(guard) or guard < 0:
        raise FacesynthError(f"model.width_guard must be a PSNR cost in dB (a number >= 0) or null (off), got {value!r}")
    return guard


def candidate_widths(width: int) -> list[int]:
    """The widths tried for a requested ``width`` (px), narrowest first: :data:`BASE_WIDTH`, the
    multiple of :data:`AUTO_WIDTH`'s step half-way to ``width`` (when it lies strictly between),
    and ``width``; ``[width]`` alone when it is not wider than the base."""
    if width <= BASE_WIDTH:
        return [int(width)]
    step = AUTO_WIDTH[2]
    mid = int(round((BASE_WIDTH + width) / 2 / step)) * step
    return [BASE_WIDTH] + ([mid] if BASE_WIDTH < mid < width else []) + [int(width)]


def choose_width(widths, psnr_db, guard_db: float) -> int:
    """The widest of ``widths`` (the first is the base) whose validation PSNR ``psnr_db`` (dB:
    one per width, or one row of slices per width) is at most ``guard_db`` below the base's on
    every slice; the base when none is."""
    widths, psnr = list(widths), np.asarray(psnr_db, np.float64)
    if len(widths) != len(psnr) or not widths:
        raise ValueError(f"{len(widths)} widths for {len(psnr)} PSNR figures")
    cost = (psnr[0] - psnr).reshape(len(widths), -1).max(1)  # the worst slice
    ok = [w for w, c in zip(widths, cost, strict=True) if c <= float(guard_db) + 1e-9]  # a cost of exactly the guard is in
    return max(ok) if ok else widths[0]


def guard_width(seq, model_seq, rows: np.ndarray, model_cfg: FaceModelConfig, name: str, params: dict,
                sadm_cfg: SADMConfig, common: np.ndarray, feather: float, seed: int = 0
                ) -> tuple[FaceModel, np.ndarray, dict | None]:
    """The face model and its training textures (as :meth:`FaceModel.fit_with_textures` on
    ``model_seq`` and ``rows``) at the width chosen under ``model_cfg.width_guard`` (off, or no
    width wider than 128 asked for: the width asked for), and the report (None when off):
    ``guard_db``, ``requested``, ``chosen``, the candidates' ``width``, ``psnr_db`` (per slice),
    ``cost_db`` (the worst slice's, against the base), the ``slices`` (``val_rows`` [start, stop)
    and ``fit_frames``, positions in ``rows``), ``seconds``. ``seq``: the training sequence (its
    landmarks drive the SADM); ``common``: (len(seq), 68, 2) dlib landmarks of the common region."""
    guard = check_width_guard(model_cfg.width_guard)
    rows = np.asarray(rows)
    width = reference_width(model_cfg.reference_width, model_seq.landmarks[rows])
    widths = candidate_widths(width)
    if guard is None or len(widths) == 1:  # nothing to guard: the width asked for
        model, tex = FaceModel.fit_with_textures(model_seq, model_cfg, rows=rows)
        if guard is None:
            return model, tex, None
        model.meta["width_guard"] = report = _report(guard, model_cfg, widths, [[]], width, [], 0.0)
        return model, tex, report
    if common is None:
        raise FacesynthError("model.width_guard needs the common region's landmarks (eval.common_region=true and "
                             "a sequence with frames)")
    t0 = time.perf_counter()
    n_val = validation_size(resolve_sadm_config(name, sadm_cfg), len(rows))
    stops = slice_stops(len(rows), n_val)
    slices = [{"val_rows": [stop - n_val, stop], "fit_frames": fit_size(stop, n_val)} for stop in stops]
    psnr = []
    for w in widths:
        cfg_w = replace(model_cfg, reference_width=w, restore=False, detail=0.0)  # the filter has its own guard
        psnr.append([])
        for stop, sl in zip(stops, slices, strict=True):
            # the face model too sees only the rows before the gap: one fitted on the slice's frames
            # holds their detail in its mean and components, more of it the wider it is
            model, tex = FaceModel.fit_with_textures(model_seq, cfg_w, rows=rows[: sl["fit_frames"]], progress=False)
            _, val, pred = held_out_predictions(model, seq, rows[:stop], tex, name, params, sadm_cfg, seed, n_val)
            psnr[-1].append(psnr_common(model, pred, seq, val, common[val], feather))
        log.info("width guard: %d px: validation PSNR %s dB", w, ", ".join(f"{p:.3f}" for p in psnr[-1]))
    chosen = choose_width(widths, psnr, guard)
    report = _report(guard, model_cfg, widths, psnr, chosen, slices, time.perf_counter() - t0)
    model, tex = FaceModel.fit_with_textures(model_seq, replace(model_cfg, reference_width=chosen), rows=rows)
    model.meta["width_guard"] = report
    return model, tex, report


def _report(guard, model_cfg, widths, psnr, chosen, slices, seconds) -> dict:
    base = np.asarray(psnr[0], np.float64)
    return {"guard_db": guard, "requested": model_cfg.reference_width, "chosen": int(chosen),
            "candidates": [{"width": int(w), "psnr_db": [float(v) for v in p],
                            "cost_db": float((base - np.asarray(p)).max()) if len(p) else None}
                           for w, p in zip(widths, psnr, strict=True)],
            "slices": slices, "seconds": float(seconds)}
