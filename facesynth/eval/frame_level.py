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
import torch

from facesynth import progress
from facesynth.compositing import blend_face, composite
from facesynth.eval import perceptual
from facesynth.eval.common_region import REGIONS, hull_box, region_masks
from facesynth.eval.sharpness import median_table, sharpness

MARGIN = 8  # px around the crops' footprint: > feather erosion + Gaussian support + bilinear reach
LPIPS_REGIONS = {"face": ("whole",), "eyes": ("eyes",), "mouth": ("mouth_interior", "lips")}
"""LPIPS's regions, as unions of the common region's parts (:data:`REGIONS`)."""
LPIPS_ROWS = ("sadm", "oracle", "rewarp")


class _LpipsPool:
    """Per-frame LPIPS of rendered-over-real region crops against the real ones, scored in
    batches (each real crop's features computed once for every row); ``scores``: {region:
    {row: [(frame position, LPIPS)]}}."""

    def __init__(self, batch: int = 16):
        self.batch, self.pending, self.scores = batch, [], {}

    def add(self, region: str, j: int, real: np.ndarray, shown: dict[str, np.ndarray]) -> None:
        self.pending.append((region, j, real, shown))
        if len(self.pending) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        net = perceptual.load()
        rows = list(self.pending[0][3])
        with torch.no_grad():
            real = net.features(perceptual.to_tensor(np.stack([p[2] for p in self.pending])))
            for row in rows:
                d = net.distance(real, net.features(perceptual.to_tensor(np.stack([p[3][row] for p in self.pending]))))
                for (region, j, *_), v in zip(self.pending, d.numpy(), strict=True):
                    self.scores.setdefault(region, {}).setdefault(row, []).append((j, float(v)))
        self.pending = []

    def medians(self) -> dict[str, dict[str, float]]:
        self.flush()
        return {reg: {row: float(np.median([s for _, s in v])) for row, v in rows.items()} for reg, rows in self.scores.items()}

    def per_frame(self, n: int) -> dict[str, dict[str, np.ndarray]]:
        """{region: {row: (n,) LPIPS per frame position, NaN where the region has no pixels}}."""
        self.flush()
        out = {}
        for reg, rows in self.scores.items():
            for row, v in rows.items():
                a = np.full(n, np.nan)
                a[[j for j, _ in v]] = [s for _, s in v]
                out.setdefault(reg, {})[row] = a
        return out


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


def _union(a: tuple, b: tuple) -> tuple:
    return min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])


def _place(mask: np.ndarray, src: tuple, dst: tuple) -> np.ndarray:
    """A bool mask over frame box ``src`` (y0, y1, x0, x1) re-cut to frame box ``dst`` (False outside ``src``)."""
    out = np.zeros((dst[1] - dst[0], dst[3] - dst[2]), bool)
    y0, y1, x0, x1 = max(src[0], dst[0]), min(src[1], dst[1]), max(src[2], dst[2]), min(src[3], dst[3])
    if y1 > y0 and x1 > x0:
        out[y0 - dst[0] : y1 - dst[0], x0 - dst[2] : x1 - dst[2]] = mask[y0 - src[0] : y1 - src[0], x0 - src[2] : x1 - src[2]]
    return out


def frame_level(model, predict, seq, rows, tex_te, oracle, cfg, seed, keys, noisy, n_grid: int = 6, common=None):
    """Pooled frame-level PSNR per row and noise level, per-frame PSNR, and grid tiles.

    Parameters
    ----------
    model : FaceModel; predict : callable (N, 68, 2) landmarks -> (N, C * M) textures
    rows : (N_test,) sequence rows of the test frames; tex_te, oracle : (N_test, C * M)
    cfg : EvalConfig (noise, max_test_frames, feather, batch_size); keys : noise keys
    noisy : callable (landmarks, sigma, seed) -> noisy landmarks
    common : (N_test, 68, 2) dlib landmarks of the test frames, or None: also measure over
        their common region (:mod:`facesynth.eval.common_region`)

    Returns
    -------
    psnr : {row: {noise key: dB}}; with ``common``, also ``psnr["common"]``:
        {region: {row: {noise key: dB}}} for the regions of :data:`REGIONS`, and
        ``psnr["common_shares"]``: {region: its pixels / the whole region's, over the frames
        evaluated}, and ``psnr["sharpness"]``: {region: {row: median over frames of the
        rendered face's Sobel energy over the real frame's}} at sigma 0, pasted with
        ``blend_face`` (:mod:`facesynth.eval.sharpness`), and, when LPIPS is installed
        (:mod:`facesynth.eval.perceptual`), ``psnr["lpips"]``: {face, eyes, mouth: {row: median
        over frames of LPIPS}} at sigma 0 for rows :data:`LPIPS_ROWS`, each region's square box
        (:func:`~facesynth.eval.perceptual.region_box` of its common-region pixels in the real
        frame) of the face pasted as for PSNR (feathered, no colour match) against the real
        frame's, both resized to 224 px (the caller pops all four); a region with no pixels in
        any evaluated frame is left out of all of them
    per_frame : {"index": (n,) test-row positions evaluated, "psnr": {row: (n,) dB at sigma 0}};
        with ``common`` also "psnr_common": {row: (n,) dB over the whole common region} and,
        with LPIPS, "lpips": {face, eyes, mouth: {row: (n,) LPIPS, NaN where the region is empty}}
    grid : list of dicts (real, synth uint8 crops, frame row, psnr)
    """
    pick = subset(len(rows), cfg.max_test_frames)
    n_model = model.mean_shape.shape[0]  # the landmarks may hold more points (irises) than the face model's
    n = len(pick)
    common = None if common is None else np.asarray(common)[pick]
    lm = seq.landmarks[rows[pick]]
    mean = np.broadcast_to(np.clip(model.appearance_pca.mean, 0, 1), (n, tex_te.shape[1]))
    # each frame's noise is seeded by its row, so a frame gets the same noise in any subset
    lm_noisy = {k: np.concatenate([noisy(lm[j : j + 1], s, seed + 17 * int(r)) for j, r in enumerate(rows[pick])])
                for s, k in zip(cfg.noise, keys, strict=True)}
    sources = {"sadm": {k: predict(v) for k, v in lm_noisy.items()}, "mean_texture": mean, "oracle": oracle[pick],
               "rewarp": tex_te[pick]}
    sq = {name: {k: np.zeros((n, 2)) for k in keys} for name in sources}
    sq_common = {reg: {name: {k: np.zeros((n, 2)) for k in keys} for name in sources} for reg in REGIONS}
    sharp = {name: {reg: [] for reg in REGIONS} for name in sources}  # per frame, sigma 0 (common region only)
    show = set(subset(n, n_grid).tolist())
    k0 = keys[[float(s) for s in cfg.noise].index(0.0)] if 0.0 in [float(s) for s in cfg.noise] else keys[0]
    grid = []
    lp = _LpipsPool() if common is not None and perceptual.available() else None
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
            # only the regions' pixels are compared: paste into their bounding box plus a margin
            # (alpha at a pixel depends on the mask within erosion + blur reach < MARGIN)
            ys, xs = np.nonzero(region)
            box = (max(y0 + ys.min() - MARGIN, 0), min(y0 + ys.max() + 1 + MARGIN, frame.shape[0]),
                   max(x0 + xs.min() - MARGIN, 0), min(x0 + xs.max() + 1 + MARGIN, frame.shape[1]))
            if common is not None:
                box = _union(box, hull_box(common[j], frame.shape[:2], MARGIN))
            region = _place(region, (y0, y1, x0, x1), box)
            regions = region_masks(common[j], box) if common is not None else {}
            y0, y1, x0, x1 = box
            sub = frame[y0:y1, x0:x1]
            sub_f = sub.astype(np.float64)
            boxes, shown_crops = {}, {}
            if lp is not None:
                for reg, parts in LPIPS_REGIONS.items():
                    b_ = perceptual.region_box(np.logical_or.reduce([regions[p] for p in parts]))
                    if b_ is not None:
                        boxes[reg] = (b_, perceptual.region_crop(sub, b_))
                        shown_crops[reg] = {}
            for k in keys:
                img, msk, plc = crops[k]
                for i, name in enumerate(sources):
                    r = i * len(idx) + b
                    out = composite(img[r], msk[r], _shift(plc[r], y0, x0), sub, cfg.feather)
                    d2 = ((out - sub_f) ** 2).sum(-1)
                    sq[name][k][j] = (float(d2[region].sum()), 3 * int(region.sum()))
                    for reg, m in regions.items():
                        sq_common[reg][name][k][j] = (float(d2[m].sum()), 3 * int(m.sum()))
                    if k == k0 and name in LPIPS_ROWS:
                        for reg, (b_, _) in boxes.items():
                            shown_crops[reg][name] = perceptual.region_crop(out, b_)
                    if regions and k == k0:
                        shown = blend_face(img[r], msk[r], _shift(plc[r], y0, x0), sub)
                        for reg, v in sharpness(shown, sub, regions).items():
                            sharp[name][reg].append(v)
                    if name == "sadm" and k == k0 and j in show:
                        ys, xs = np.nonzero(region)
                        crop_box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
                        grid.append({"real": sub[crop_box].copy(), "synth": out[crop_box].copy(), "frame": int(rows[pick[j]]),
                                     "psnr": _db(*sq[name][k][j])})
            for reg, (_, real_crop) in boxes.items():
                lp.add(reg, j, real_crop, shown_crops[reg])
            bar.update(1)
    bar.close()
    pooled = {name: {k: _db(*v.sum(0)) for k, v in d_.items()} for name, d_ in sq.items()}
    if common is not None:
        # a part no evaluated frame shows (the mouth interior of a clip whose mouth stays
        # closed) is left out of the three tables
        counts = {reg: float(per["sadm"][k0][:, 1].sum()) for reg, per in sq_common.items()}
        shown = [reg for reg, c in counts.items() if c > 0]
        pooled["common"] = {reg: {name: {k: _db(*v.sum(0)) for k, v in sq_common[reg][name].items()} for name in sources}
                            for reg in shown}
        pooled["common_shares"] = {reg: counts[reg] / max(counts["whole"], 1.0) for reg in shown}
        pooled["sharpness"] = {reg: t for reg, t in median_table(sharp).items() if reg in shown}
        if lp is not None:
            pooled["lpips"] = lp.medians()
    per_frame = {"index": pick, "psnr": {name: np.array([_db(*r) for r in d_[k0]]) for name, d_ in sq.items()}}
    if common is not None:
        per_frame["psnr_common"] = {name: np.array([_db(*r) for r in d_[k0]]) for name, d_ in sq_common["whole"].items()}
        if lp is not None:
            per_frame["lpips"] = lp.per_frame(n)
    return pooled, per_frame, grid


def psnr_common(model, textures: np.ndarray, seq, rows: np.ndarray, common: np.ndarray, feather: float = 2.0,
                batch: int = 32) -> float:
    """Pooled PSNR (dB) of ``textures`` (len(rows), C * M) rendered by ``model`` at the landmarks of
    ``rows`` of ``seq``, pasted (feathered, as :func:`frame_level`) into their real frames, over the
    common region (``whole``) of the rows' (len(rows), 68, 2) dlib landmarks ``common``:
    ``psnr_frame_common``'s figure at sigma 0 for one row of textures. The region does not depend
    on the model, so models at different reference widths are judged on the same pixels."""
    rows = np.asarray(rows)
    n_model = model.mean_shape.shape[0]
    sum_sq, count = 0.0, 0
    frames = seq.iter_frames(rows)
    for start in range(0, len(rows), batch):
        idx = np.arange(start, min(start + batch, len(rows)))
        img, msk, plc = model.render(textures[idx], seq.landmarks[rows[idx]][:, :n_model])
        for b, j in enumerate(idx):
            frame = next(frames)
            y0, y1, x0, x1 = box = hull_box(common[j], frame.shape[:2], MARGIN)
            whole = region_masks(common[j], box)["whole"]
            sub = frame[y0:y1, x0:x1]
            out = composite(img[b], msk[b], _shift(plc[b], y0, x0), sub, feather)
            sum_sq += float(((out - sub.astype(np.float64)) ** 2).sum(-1)[whole].sum())
            count += 3 * int(whole.sum())
    return _db(sum_sq, count)


def _db(sum_sq: float, count: float) -> float:
    """PSNR (peak 255) of a summed squared error over ``count`` values."""
    return float(10 * np.log10(255.0**2 / (sum_sq / max(count, 1)))) if sum_sq > 0 else float("inf")
