"""Figures of reenactment, shared by ``bench/runtime/reenact.py`` and the tests.

* coverage: per frame, the share of the avatar's face-outline hull (convex hull of the
  rendered landmarks, eroded 3 px) that the rendered mask covers (placed in the frame);
* expression following: Pearson r between the driver's and the avatar's mouth opening
  (inner-lip gap / inter-ocular) and eye opening (eyelid gap / inter-ocular), measured on
  the landmarks the avatar was rendered with (their iBUG-68 view for another scheme);
* identity: median jaw width (0-16) / nose-bridge-to-chin (27-8) of the rendered avatar
  against the avatar's own training frames (relative difference);
* self-driving: frame-level PSNR of a clip's held-out frames rendered with relative and
  with absolute motion, each composited into the real frame, over the face hull;
* speed: batch-1 one-thread model call (``Renderer.render``) and retargeting
  (``Retargeter.one``) CPU times in the same process.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from facesynth.compositing import blend_rendered
from facesynth.landmarks import ibug68_view
from facesynth.metrics import psnr
from facesynth.neutral import mouth_open
from facesynth.retarget import Retargeter, eye_open
from facesynth.runtime.reenact import Reenactor, driver_neutral_of


def shape_ratio(landmarks: np.ndarray) -> np.ndarray:
    """(N, 68, 2) -> (N,) jaw width (points 0-16) / nose bridge top to chin (27-8)."""
    lm = np.asarray(landmarks, np.float64)
    return np.linalg.norm(lm[:, 0] - lm[:, 16], axis=-1) / np.linalg.norm(lm[:, 27] - lm[:, 8], axis=-1)


def hull_mask(landmarks: np.ndarray, size: tuple[int, int], erode: int = 3) -> np.ndarray:
    """bool (H, W): convex hull of (P, 2) landmarks, eroded by ``erode`` pixels."""
    m = np.zeros(size, np.uint8)
    hull = cv2.convexHull(np.round(landmarks * 16).astype(np.int32))
    cv2.fillConvexPoly(m, hull, 1, lineType=cv2.LINE_8, shift=4)
    if erode:
        m = cv2.erode(m, np.ones((2 * erode + 1, 2 * erode + 1), np.uint8))
    return m > 0


def placed_mask(mask: np.ndarray, placement: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """bool (H, W): a crop mask (H_c, W_c) placed in the frame (nearest neighbour)."""
    h, w = size
    return cv2.warpAffine(mask.astype(np.float32), placement.astype(np.float64), (w, h), flags=cv2.INTER_NEAREST) > 0.5


def drive(model_path, driver: np.ndarray, motion: str = "relative", neutral: np.ndarray | None = None,
          frames: bool = False, sheet_rows=()) -> dict:
    """Drive ``model_path`` with (T, P, 2) ``driver`` landmarks (the model's scheme), frame by frame.

    Returns {"landmarks": (T, P, 2) rendered avatar landmarks, "coverage": (T,) hull
    coverage, "frames": {row: uint8 frame} for ``sheet_rows``}.
    """
    if neutral is None and motion == "relative":
        neutral = driver_neutral_of(driver)[0]
    re = Reenactor(model_path, neutral, motion)
    size = re.background.shape[:2] if re.background is not None else None
    out_lm = np.zeros(driver.shape, np.float32)
    cov = np.zeros(len(driver))
    shown = {}
    for i, lm in enumerate(driver):
        a = re.retarget(lm)
        out_lm[i] = a
        crops, masks, place = re.renderer.render(a[None])
        sz = size or (int(a[:, 1].max()) + 8, int(a[:, 0].max()) + 8)
        hull = hull_mask(a, sz)
        cov[i] = (placed_mask(masks[0, 0], place[0], sz) & hull).sum() / max(1, hull.sum())
        if i in sheet_rows:
            bg = re.frame_warp(a) if re.full_frame else re.background
            shown[i] = blend_rendered(crops, masks, place, bg, 0, re.feather, re.match_colour)
    return {"landmarks": out_lm, "coverage": cov, "frames": shown}


def pair_figures(model_path, driver: np.ndarray, avatar_train: np.ndarray, sheet_rows=()) -> dict:
    """The acceptance figures of one (avatar model, driver landmarks) pair (relative motion)."""
    res = drive(model_path, driver, "relative", sheet_rows=sheet_rows)
    a, d68 = ibug68_view(res["landmarks"]), ibug68_view(driver)
    own = float(np.median(shape_ratio(ibug68_view(avatar_train))))
    got = float(np.median(shape_ratio(a)))
    drv = float(np.median(shape_ratio(d68)))
    out = {
        "frames": int(len(driver)),
        "coverage_min": round(float(res["coverage"].min()), 5),
        "coverage_median": round(float(np.median(res["coverage"])), 5),
        "frames_coverage_below_99": int((res["coverage"] < 0.99).sum()),
        "mouth_open_r": round(float(np.corrcoef(mouth_open(d68), mouth_open(a))[0, 1]), 4),
        "eye_open_r": round(float(np.corrcoef(eye_open(d68), eye_open(a))[0, 1]), 4),
        "shape_ratio_avatar_own": round(own, 4),
        "shape_ratio_rendered": round(got, 4),
        "shape_ratio_driver": round(drv, 4),
        "shape_ratio_rel_diff": round(abs(got - own) / own, 4),
        "shape_ratio_rel_diff_absolute_motion": round(abs(drv - own) / own, 4),
    }
    return {"figures": out, "frames": res["frames"], "landmarks": res["landmarks"]}


def self_driving_psnr(model_path, landmarks: np.ndarray, frames, neutral: np.ndarray) -> dict:
    """Frame-level PSNR (dB, over the face hull) of held-out frames of the avatar's own clip
    driven by their own landmarks, relative vs absolute motion; ``frames`` yields the real
    uint8 RGB frames of the rows of ``landmarks``; ``neutral`` the driver's neutral."""
    rel = Reenactor(model_path, neutral, "relative", match_colour=False, full_frame=False)  # into the real frame
    ab = Reenactor(model_path, None, "absolute", match_colour=False, full_frame=False)
    scores = {"relative": [], "absolute": []}
    for lm, real in zip(landmarks, frames, strict=False):
        hull = hull_mask(lm, real.shape[:2], erode=0)
        for name, re in (("relative", rel), ("absolute", ab)):
            re.background = real
            out, _ = re.step(lm)
            scores[name].append(psnr(out, real, hull))
    r, a = float(np.mean(scores["relative"])), float(np.mean(scores["absolute"]))
    return {"frames": len(scores["relative"]), "psnr_relative_db": round(r, 3), "psnr_absolute_db": round(a, 3),
            "difference_db": round(r - a, 3)}


def speed(model_path, driver: np.ndarray, avatar_neutral_model=None, reps: int = 500) -> dict:
    """Median CPU time (µs) per frame at batch 1, one thread: the model call and retargeting."""
    re = Reenactor(model_path, driver_neutral_of(driver)[0], "relative", threads=1)
    ret: Retargeter = re._retarget
    x = [f.astype(np.float64) for f in driver[: min(len(driver), 50)]]
    lm = [ret.one(f).astype(np.float32)[None] for f in x]
    t_model, t_ret = [], []
    for k in range(reps):  # interleaved, so both see the same load
        f = k % len(x)
        t0 = time.process_time()
        re.renderer.render(lm[f])
        t1 = time.process_time()
        ret.one(x[f])
        t2 = time.process_time()
        t_model.append(t1 - t0)
        t_ret.append(t2 - t1)
    m, r = float(np.median(t_model)) * 1e6, float(np.median(t_ret)) * 1e6
    return {"renderer_us": round(m, 1), "retarget_us": round(r, 1), "retarget_share": round(r / m, 4), "reps": reps}
