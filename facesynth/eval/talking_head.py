"""The report's talking-head section: the run's avatar drives itself on its held-out frames.

Each held-out frame's landmarks are retargeted onto the avatar (relative motion, the
driver's neutral = the avatar's own, :class:`facesynth.retarget.Retargeter` with the shape
clamp) and rendered three ways, compared with the real frame: *static* (the avatar's neutral
frame unchanged), *warp* (that frame warped with the landmarks, no synthesised face;
:class:`facesynth.runtime.fullframe.FrameWarp`) and *full* (the synthesised face composited
into the warped frame, :func:`facesynth.compositing.blend_face`): the numpy pipeline that
``facesynth export --talking-head`` puts in one graph. The avatar is the exported one's
(:func:`facesynth.onnx.avatar.avatar_metadata`: its neutral among the training frames, its
shape PCA, that frame as JPEG). Measures: PSNR (dB) and SSIM over the head region (the real
landmarks' hull grown to hair and neck, :func:`facesynth.runtime.fullframe.head_region`) and
over the whole frame, mean over up to ``frames`` evenly spaced held-out frames
(``bench/runtime/talking_head.py`` adds the detector-based figures on other drivers). The
*warp*'s outline on up to ``OUTLINE_FRAMES`` of them: how far its grid's map departs from the
exact piecewise affine map along the head's outline and the staircase energy that draws
(:func:`facesynth.eval.jaggedness.outline_figures`, medians over the frames).
"""

from __future__ import annotations

import numpy as np
import torch

from facesynth.compositing import blend_rendered
from facesynth.eval.jaggedness import exact_warp, outline_figures
from facesynth.eval.strip import box_tile
from facesynth.landmarks import ibug68_view
from facesynth.metrics import psnr, ssim
from facesynth.onnx.avatar import avatar_metadata
from facesynth.retarget import RETARGET_SCHEMES, Retargeter
from facesynth.runtime.fullframe import head_region
from facesynth.runtime.reenact import Avatar

RENDERERS = ("static", "warp", "full")
MEASURES = ("psnr_head_db", "ssim_head", "psnr_frame_db", "ssim_frame")
OUTLINE_FRAMES = 8  # frames the warp's outline is measured on (the exact map costs about a second each)


def talking_head_figures(syn, seq, train_rows: np.ndarray, test_rows: np.ndarray, frames: int = 40,
                         strip: int = 6, height: int = 128) -> tuple[dict, list[dict]]:
    """(figures, strip tiles) of the run's avatar driving itself (module docstring), or ({}, [])
    when the clip has no frames or its scheme cannot be retargeted.

    figures: {"frames": n, "neutral_row": row, "ring_scale": the warp's head ring (chosen on the
    training frames, :mod:`facesynth.onnx.headmotion`), RENDERER: {MEASURE: mean}, "outline":
    {"map_px_p99", "map_px_max", "staircase"} (module docstring)}; strip tiles: the
    :mod:`facesynth.eval.strip` tiles ({"frame", "real", "synth"}: the real held-out frame and
    *full*) of ``strip`` of those frames, one frame box for all, ``height`` px high."""
    scheme = str(getattr(syn, "scheme", "ibug68"))
    if not seq.has_frames or scheme not in RETARGET_SCHEMES or not len(test_rows):
        return {}, []
    meta = avatar_metadata(syn, seq.landmarks[train_rows], train_rows, seq)
    avatar = Avatar({**meta, "landmark_scheme": scheme}, seq.name)
    retarget = Retargeter(avatar.neutral, avatar.neutral, avatar.shape_space, "relative", scheme=scheme)
    warp = avatar.frame_warp()
    rows = np.asarray(test_rows)[np.unique(np.linspace(0, len(test_rows) - 1, min(frames, len(test_rows))).round().astype(int))]
    shown = set(rows[np.unique(np.linspace(0, len(rows) - 1, min(strip, len(rows))).round().astype(int))].tolist())
    sums = {r: dict.fromkeys(MEASURES, 0.0) for r in RENDERERS}
    outline_rows = set(rows[np.unique(np.linspace(0, len(rows) - 1, min(OUTLINE_FRAMES, len(rows))).round().astype(int))].tolist())
    exact, outline = exact_warp(warp), []
    pairs = []
    for row, real in zip(rows, seq.iter_frames(rows), strict=True):
        real = np.asarray(real)
        a = retarget.one(np.asarray(seq.landmarks[row], np.float64)).astype(np.float32)
        with torch.no_grad():
            crop, mask, place = (t.numpy() for t in syn(torch.from_numpy(a[None])))
        bg = warp(a)
        full = blend_rendered(crop, mask, place, bg)
        head = head_region(ibug68_view(seq.landmarks[row]), (real.shape[1], real.shape[0]))
        for name, img in zip(RENDERERS, (avatar.background, bg, full), strict=True):
            for key, value in zip(MEASURES, (psnr(img, real, head), ssim(img, real, head), psnr(img, real),
                                             ssim(img, real)), strict=True):
                sums[name][key] += float(value)
        if int(row) in outline_rows:
            outline.append(outline_figures(warp, a, exact))
        if int(row) in shown:
            pairs.append((int(row), real, full, ibug68_view(seq.landmarks[row])))
    figures = {"frames": len(rows), "neutral_row": int(meta["avatar_neutral_row"]), "ring_scale": warp.ring_scale}
    figures.update({r: {k: round(v / len(rows), 4 if k.startswith("ssim") else 2) for k, v in m.items()}
                    for r, m in sums.items()})
    figures["outline"] = {k: round(float(np.median([o[k] for o in outline])), 4) for k in outline[0]}
    return figures, _tiles(pairs, height)


def _tiles(pairs: list, height: int, margin: float = 0.6) -> list[dict]:
    """Strip tiles cut from one box round the frames' heads (their landmarks' box grown by
    ``margin`` of its size: hair and neck), scaled to ``height``."""
    if not pairs:
        return []
    pts = np.concatenate([p[3] for p in pairs])
    lo, hi = pts.min(0), pts.max(0)
    pad = margin * (hi - lo)
    return [box_tile(row, real, full, lo - pad, hi + pad, height) for row, real, full, _ in pairs]
