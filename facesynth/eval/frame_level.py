"""Whole-pipeline PSNR in the original frames (``psnr_frame`` of ``metrics.json``).

For each evaluated test frame and noise level, the four rows (``sadm``, ``mean_texture``,
``oracle``, ``rewarp``) are rendered at the noisy landmarks, pasted (feathered) into the
clean frame and compared with it over the face region of the clean landmarks. Squared
errors are pooled over frames; per-frame PSNR is kept for the PSNR-over-time plot.

Speed: predictions and renders are batched over frames, and the paste works inside a
region of interest around the face (the union of the crops' footprints plus a margin
wider than the feathering), which gives the same pixels as pasting into the whole frame
(outside the footprint the frame is untouched) at a fraction of the cost on 720p clips.
"""

from __future__ import annotations

import cv2
import numpy as np

from facesynth import progress
from facesynth.imaging import composite

MARGIN = 8  # px around the crops' footprint: > feather erosion + Gaussian support + bilinear reach


def subset(n: int, max_frames: int | None) -> np.ndarray:
    """Indices of ``max_frames`` evenly spaced items out of ``n`` (all when None/0 or n is smaller)."""
    if not max_frames or n <= max_frames:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_frames).round().astype(int))


def _roi(places: np.ndarray, crop_hw: tuple[int, int], frame_hw: tuple[int, int]) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): frame box covering every placed crop in ``places`` (K, 2, 3)."""
    h, w = crop_hw
    corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], np.float64)
    pts = np.einsum("kij,cj->kci", places, corners).reshape(-1, 2)
    x0, y0 = np.floor(pts.min(0)).astype(int) - MARGIN
    x1, y1 = np.ceil(pts.max(0)).astype(int) + MARGIN
    fh, fw = frame_hw
    return max(y0, 0), min(y1, fh), max(x0, 0), min(x1, fw)


def _shift(place: np.ndarray, y0: int, x0: int) -> np.ndarray:
    p = place.copy()
    p[0, 2] -= x0
    p[1, 2] -= y0
    return p


def frame_level(model, predict, seq, rows, tex_te, oracle, cfg, seed, keys, noisy, n_grid: int = 6):
    """Pooled frame-level PSNR per row and noise level, per-frame PSNR, and grid tiles.

    Parameters
    ----------
    model : FaceModel; predict : callable (N, 68, 2) landmarks -> (N, C * M) textures
    rows : (N_test,) sequence rows of the test frames; tex_te, oracle : (N_test, C * M)
    cfg : EvalConfig (noise, max_test_frames, feather, batch_size); keys : noise keys
    noisy : callable (landmarks, sigma, seed) -> noisy landmarks

    Returns
    -------
    psnr : {row: {noise key: dB}}
    per_frame : {"index": (n,) test-row positions evaluated, "psnr": {row: (n,) dB at sigma 0}}
    grid : list of dicts (real, synth uint8 crops, frame row, psnr)
    """
    pick = subset(len(rows), cfg.max_test_frames)
    n_model = model.mean_shape.shape[0]  # the landmarks may hold more points (irises) than the face model's
    n = len(pick)
    lm = seq.landmarks[rows[pick]]
    mean = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), (n, tex_te.shape[1]))
    # each frame's noise is seeded by its row, so a frame gets the same noise in any subset
    lm_noisy = {k: np.concatenate([noisy(lm[j : j + 1], s, seed + 17 * int(r)) for j, r in enumerate(rows[pick])])
                for s, k in zip(cfg.noise, keys, strict=True)}
    sources = {"sadm": {k: predict(v) for k, v in lm_noisy.items()}, "mean_texture": mean, "oracle": oracle[pick],
               "rewarp": tex_te[pick]}
    sq = {name: {k: np.zeros((n, 2)) for k in keys} for name in sources}
    show = set(subset(n, n_grid).tolist())
    k0 = keys[[float(s) for s in cfg.noise].index(0.0)] if 0.0 in [float(s) for s in cfg.noise] else keys[0]
    grid = []
    bs = cfg.batch_size
    frames = seq.iter_frames(rows[pick])
    bar = progress.bar(total=n, desc="frame-level PSNR", unit="frame")
    for start in range(0, n, bs):
        idx = np.arange(start, min(start + bs, n))
        _, cmask, cplace = model.render(mean[idx], lm[idx, :n_model])
        crops = {}
        for k in keys:
            texs = np.concatenate([(src[k] if isinstance(src, dict) else src)[idx] for src in sources.values()])
            crops[k] = model.render(texs, np.tile(lm_noisy[k][idx, :n_model], (len(sources), 1, 1)))
        for b, j in enumerate(idx):
            frame = next(frames)
            places = np.concatenate([cplace[b : b + 1]] + [crops[k][2][b :: len(idx)] for k in keys])
            y0, y1, x0, x1 = _roi(places, cmask.shape[1:3], frame.shape[:2])
            region = cv2.warpAffine(cmask[b], _shift(cplace[b], y0, x0), (x1 - x0, y1 - y0)) > 0.999
            region = cv2.erode(region.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            # only the region's pixels are compared: paste into its bounding box plus a margin
            # (alpha at a pixel depends on the mask within erosion + blur reach < MARGIN)
            ys, xs = np.nonzero(region)
            ry0, ry1 = max(ys.min() - MARGIN, 0), min(ys.max() + 1 + MARGIN, y1 - y0)
            rx0, rx1 = max(xs.min() - MARGIN, 0), min(xs.max() + 1 + MARGIN, x1 - x0)
            region = region[ry0:ry1, rx0:rx1]
            y0, y1, x0, x1 = y0 + ry0, y0 + ry1, x0 + rx0, x0 + rx1
            sub = frame[y0:y1, x0:x1]
            sub_r = sub[region].astype(np.float64)
            for k in keys:
                img, msk, plc = crops[k]
                for i, name in enumerate(sources):
                    r = i * len(idx) + b
                    out = composite(img[r], msk[r], _shift(plc[r], y0, x0), sub, cfg.feather)
                    d = out[region] - sub_r
                    sq[name][k][j] = (float((d**2).sum()), d.size)
                    if name == "sadm" and k == k0 and j in show:
                        ys, xs = np.nonzero(region)
                        box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
                        grid.append({"real": sub[box].copy(), "synth": out[box].copy(), "frame": int(rows[pick[j]]),
                                     "psnr": _db(*sq[name][k][j])})
            bar.update(1)
    bar.close()
    pooled = {name: {k: _db(*v.sum(0)) for k, v in d_.items()} for name, d_ in sq.items()}
    per_frame = {"index": pick, "psnr": {name: np.array([_db(*r) for r in d_[k0]]) for name, d_ in sq.items()}}
    return pooled, per_frame, grid


def _db(sum_sq: float, count: float) -> float:
    """PSNR (peak 255) of a summed squared error over ``count`` values."""
    return float(10 * np.log10(255.0**2 / (sum_sq / max(count, 1)))) if sum_sq > 0 else float("inf")
