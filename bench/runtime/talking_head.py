"""Talking-head figures: the avatar's still frame, the full-frame warp alone and the whole
pipeline on the same frames; one JSON line (and contact sheets).

    OMP_NUM_THREADS=1 python -m bench.runtime.talking_head [--work /tmp/facesynth_th] [--sheets docs]
        [--clips lp_d3,...] [--stride 1] [--regressor krr]

Renderers (every avatar a model trained on the first 75 % of its clip,
``train.py data=video regressor=R eval.frame_level=false``, R from ``--regressor``, linear by
default; default export):

* ``static``: the avatar's neutral frame (the exported metadata's), unchanged;
* ``warp``: that frame warped to the avatar landmarks (:class:`FrameWarp`), no synthesised face;
* ``full``: :class:`facesynth.runtime.Reenactor` (retargeting, synthesis, full-frame warp,
  feathered colour-matched compositing);
* ``paste`` (cross pairs, detection measures only): the face composited into the still
  neutral frame (``full_frame=False``, the behaviour before the full-frame warp);
* ``oracle`` (self-reenactment, PSNR and SSIM only): the real frame composited into *warp*
  with the alpha of *full*'s face (:func:`placed_alpha`): what a perfect synthesised face
  would give, so the bound on *full* - *warp* that the compositing region leaves.
* ``warp_own`` (self-reenactment, PSNR and SSIM only): the frame warped to the held-out
  frame's own landmarks as they are (no retargeting, ``--motion absolute``): *warp* -
  *warp_own* is what the retargeting's caps and bounds cost the warp where the avatar's
  held-out frames leave its training repertoire.

Measures:

* self-reenactment, each clip's held-out last 25 % driven by its own landmarks (relative
  motion, the driver's neutral = the avatar's): PSNR and SSIM against the real frame over the
  head region (:func:`head_region` of the real landmarks: hull grown to hair and neck) and
  over the whole frame, and PSNR over the real landmarks' hull (the face alone);
* identity: Euclidean distance between dlib's face descriptor
  (``dlib_face_recognition_resnet_model_v1.dat``) of each output frame and the mean
  descriptor of 20 of the avatar's training frames; the reference is the same distance of
  30 of the avatar's own held-out real frames (median); dlib's same-person threshold is 0.6;
* one-face rate: share of output frames where dlib's HOG detector (no upsampling; once
  upsampled when it finds none) finds
  exactly one face and it overlaps the avatar landmarks' box (IoU >= 0.3);
* AKD: dlib's 68 points re-detected on the output (in the overlapping box) against the
  landmarks the avatar was rendered with, mean distance in % of their outer-eye-corner
  distance (a frame without a detection counts as missing, reported apart);
* doubled eyes: the still frame's own eyes (patches of 0.5 x 0.28 IOD round each eye of the
  avatar's neutral) searched for in the output's head box by normalised cross-correlation
  (``cv2.matchTemplate``, TM_CCOEFF_NORMED) farther than 0.3 IOD from both eyes the avatar
  is rendered with: the best score per frame (median, max) and the share of frames over
  ``DOUBLE_NCC`` (the still frame's eyes left showing beside the rendered ones: the
  one-face rate misses them, dlib finds one face where two overlap);
* flicker: mean absolute frame-to-frame change (0-255) outside the head region and inside the
  face's landmark hull;
* ``ring_scale``: the size of the warp's head ring each avatar chose at export
  (:func:`facesynth.onnx.headmotion.fit_frame_motion`).

Cross pairs (avatar <- driver): the drivers are the clips with head motion, in full.
``--sheets DIR``: ``talking_head_AVATAR_by_DRIVER.jpg``: per row, the driver frame with one of
the three largest head turns (roll and yaw against the driver's neutral) | paste | warp | full;
``talking_head_CLIP_self.jpg`` for a self pair: the real held-out frame | static | warp | full.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.harness import emit, load_average  # noqa: E402
from bench.runtime.reenact import model_for  # noqa: E402
from facesynth.compositing import placed_alpha  # noqa: E402
from facesynth.data import load_sequence, shared_clip  # noqa: E402
from facesynth.data.detect import predictor_path  # noqa: E402
from facesynth.eval.reenact import hull_mask  # noqa: E402
from facesynth.geometry import similarity_fit  # noqa: E402
from facesynth.io import atomic_path  # noqa: E402
from facesynth.landmarks import inter_ocular  # noqa: E402
from facesynth.metrics import psnr, ssim  # noqa: E402
from facesynth.neutral import select_neutral  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.runtime import Reenactor  # noqa: E402
from facesynth.runtime.fullframe import head_region  # noqa: E402
from facesynth.runtime.reenact import driver_neutral_of  # noqa: E402

CLIPS = ("lp_d3", "lp_d20", "lp_d11", "sadtalker_aoc", "vrt_face1", "vrt_face2", "vrt_face4", "vrt_face5")
PAIRS = (("lp_d20", "lp_d3"), ("vrt_face2", "lp_d11"), ("sadtalker_aoc", "vrt_face5"), ("vrt_face4", "lp_d3"),
         ("lp_d11", "sadtalker_aoc"))
SHEET_PAIRS = (("lp_d20", "lp_d3"), ("vrt_face2", "lp_d11"), ("sadtalker_aoc", "vrt_face5"), ("lp_d3", "lp_d3"))
SAME_PERSON = 0.6
IOU_MIN = 0.3
DOUBLE_NCC = 0.9  # the rendered and warped eyes score <= 0.86 on two pairs, the still eyes 0.97-1.0


class Dlib:
    """dlib's HOG detector and 68-point predictor run as ``facesynth ingest`` runs them
    (:class:`LandmarkDetector`: detection on the frame downscaled to 640 px, the predictor at
    full size; the shared clips' landmarks come from it), and dlib's face descriptor
    (face_recognition_models). Detected another way (at full size), vrt_face1's own real
    frames sit 1.9 % of the IOD off their landmarks, a bias AKD would count as the render's."""

    def __init__(self):
        import dlib

        from facesynth.data.detect import LandmarkDetector

        self.ingest = LandmarkDetector()
        self.dlib = dlib
        self.encoder = dlib.face_recognition_model_v1(str(predictor_path().parent / "dlib_face_recognition_resnet_model_v1.dat"))

    def faces(self, img: np.ndarray, box=None) -> dict:
        """Detections of a uint8 RGB frame; with ``box`` (x0, y0, x1, y1) the one overlapping it
        most: its 68 points and descriptor."""
        found, _ = self.ingest.boxes(img)
        out = {"n": len(found), "one": False, "points": None, "descriptor": None}
        if not len(found):
            return out
        best = found[0] if box is None else max(found, key=lambda d: iou(d, box))
        if box is not None and iou(best, box) < IOU_MIN:
            return out
        out["one"] = len(found) == 1
        pts = self.ingest.landmarks(img, best)
        out["points"] = pts.astype(np.float64)
        shape = self.dlib.full_object_detection(self.dlib.rectangle(*(int(round(v)) for v in best)),
                                                [self.dlib.point(int(x), int(y)) for x, y in pts])
        out["descriptor"] = np.array(self.encoder.compute_face_descriptor(np.ascontiguousarray(img), shape))
        return out


def iou(det, box) -> float:
    """Intersection over union of two (x0, y0, x1, y1) boxes."""
    x0, y0, x1, y1 = det
    ix = max(0.0, min(x1, box[2]) - max(x0, box[0]))
    iy = max(0.0, min(y1, box[3]) - max(y0, box[1]))
    inter = ix * iy
    union = (x1 - x0) * (y1 - y0) + (box[2] - box[0]) * (box[3] - box[1]) - inter
    return inter / union if union > 0 else 0.0


class StillEyes:
    """The avatar's neutral eyes as templates, found again in an output frame away from where
    its eyes should be (module docstring: doubled eyes)."""

    def __init__(self, frame: np.ndarray, neutral68: np.ndarray):
        self.iod = float(inter_ocular(neutral68))
        grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        hw, hh = int(0.25 * self.iod), int(0.14 * self.iod)
        self.templates = []
        for eye in (slice(36, 42), slice(42, 48)):
            x, y = np.round(neutral68[eye].mean(0)).astype(int)
            self.templates.append(grey[max(y - hh, 0):y + hh, max(x - hw, 0):x + hw])

    def score(self, img: np.ndarray, lm: np.ndarray) -> float:
        """Best correlation of a still eye farther than 0.3 IOD from both rendered eyes."""
        h, w = img.shape[:2]
        ys, xs = np.nonzero(head_region(lm, (w, h)))
        x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
        grey = cv2.cvtColor(np.ascontiguousarray(img[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
        eyes = np.stack([lm[36:42].mean(0), lm[42:48].mean(0)]) - (x0, y0)
        best = -1.0
        for t in self.templates:
            th, tw = t.shape
            if grey.shape[0] < th or grey.shape[1] < tw:
                continue
            ncc = cv2.matchTemplate(grey, t, cv2.TM_CCOEFF_NORMED)
            cy, cx = np.mgrid[0:ncc.shape[0], 0:ncc.shape[1]]
            cx, cy = cx + tw / 2, cy + th / 2  # template centres
            far = np.ones(ncc.shape, bool)
            for ex, ey in eyes:
                far &= np.hypot(cx - ex, cy - ey) > 0.3 * self.iod
            if far.any():
                best = max(best, float(ncc[far].max()))
        return best


def box_of(lm: np.ndarray) -> tuple:
    return (*lm.min(0), *lm.max(0))


def mean_descriptor(dl: Dlib, seq, rows, landmarks) -> np.ndarray:
    d = [dl.faces(np.asarray(seq.frame(int(r))), box_of(landmarks[r]))["descriptor"] for r in rows]
    d = [x for x in d if x is not None]
    return np.mean(d, 0)


def head_turn(lm: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """(T,) head turn of (T, 68, 2) frames against a neutral: |roll| (rad) of the similarity on
    the eye corners and nose bridge + |yaw proxy change| (nose tip's offset from the jaw's
    middle over the jaw's width)."""
    idx = [27, 36, 39, 42, 45]
    s = similarity_fit(neutral[idx], lm[:, idx])
    roll = np.arctan2(s[:, 1, 0], s[:, 0, 0])

    def yaw(x):
        return (x[..., 30, 0] - 0.5 * (x[..., 0, 0] + x[..., 16, 0])) / (x[..., 16, 0] - x[..., 0, 0])

    return np.abs(roll) + np.abs(yaw(lm) - yaw(neutral))


def top_turns(lm: np.ndarray, k: int = 3, apart: int = 10) -> list[int]:
    turn = head_turn(lm, lm[select_neutral(lm)[0]])
    picks = []
    for i in np.argsort(-turn):
        if all(abs(int(i) - p) >= apart for p in picks):
            picks.append(int(i))
        if len(picks) == k:
            break
    return sorted(picks)


class Track:
    """Per-renderer accumulators over a sequence of output frames."""

    def __init__(self, dl: Dlib | None, ref: np.ndarray | None, eyes: StillEyes | None = None):
        self.dl, self.ref, self.eyes, self.double = dl, ref, eyes, []
        self.one, self.ident, self.akd, self.missing = [], [], [], 0
        self.flick_bg, self.flick_face, self.prev = [], [], None
        self.psnr_head, self.psnr_frame, self.ssim_head, self.ssim_frame, self.psnr_face = [], [], [], [], []

    def add(self, img: np.ndarray, lm: np.ndarray, real: np.ndarray | None = None, real_lm=None):
        size = img.shape[1::-1]
        head = head_region(lm, size)
        face = hull_mask(lm, img.shape[:2], erode=0)
        if self.prev is not None:
            diff = np.abs(img.astype(np.float32) - self.prev).mean(-1)
            self.flick_bg.append(float(diff[~head].mean()) if (~head).any() else 0.0)
            self.flick_face.append(float(diff[face].mean()))
        self.prev = img.astype(np.float32)
        if real is not None:
            m = head_region(real_lm, size)
            self.psnr_head.append(psnr(img, real, m))
            self.psnr_face.append(psnr(img, real, hull_mask(real_lm, img.shape[:2], erode=0)))
            self.psnr_frame.append(psnr(img, real))
            self.ssim_head.append(ssim(img, real, m))
            self.ssim_frame.append(ssim(img, real))
        if self.eyes is not None:
            self.double.append(self.eyes.score(img, lm))
        if self.dl is not None:
            f = self.dl.faces(img, box_of(lm))
            self.one.append(f["one"])
            if f["points"] is None:
                self.missing += 1
            else:
                self.akd.append(100.0 * float(np.linalg.norm(f["points"] - lm, axis=1).mean() / inter_ocular(lm)))
                self.ident.append(float(np.linalg.norm(f["descriptor"] - self.ref)))

    def summary(self) -> dict:
        def r(x, d=3):
            return None if x is None or not np.isfinite(x) else round(float(x), d)

        out = {}
        if self.psnr_head:
            out.update(psnr_head_db=r(np.mean(self.psnr_head), 2), ssim_head=r(np.mean(self.ssim_head), 4),
                       psnr_frame_db=r(np.mean(self.psnr_frame), 2), ssim_frame=r(np.mean(self.ssim_frame), 4),
                       psnr_face_db=r(np.mean(self.psnr_face), 2))
        if self.dl is not None:
            out.update(frames=len(self.one), one_face_rate=r(np.mean(self.one), 4), no_face_or_elsewhere=self.missing)
            if self.ident:
                out.update(identity_median=r(np.median(self.ident)), identity_max=r(np.max(self.ident)),
                           identity_frames_over_0_6=int((np.asarray(self.ident) >= SAME_PERSON).sum()),
                           akd_median_pct_iod=r(np.median(self.akd), 2), akd_p95_pct_iod=r(np.percentile(self.akd, 95), 2))
        if self.double:
            out.update(still_eyes_ncc_median=r(np.median(self.double)), still_eyes_ncc_max=r(np.max(self.double)),
                       doubled_eyes_rate=r(np.mean(np.asarray(self.double) >= DOUBLE_NCC), 4))
        if self.flick_bg:
            out.update(flicker_background=r(np.mean(self.flick_bg)), flicker_face=r(np.mean(self.flick_face)))
        return out


def sheet_image(rows: list[list[np.ndarray]], height: int = 200) -> np.ndarray:
    def thumb(img):
        h, w = img.shape[:2]
        return cv2.resize(img, (int(round(w * height / h)), height), interpolation=cv2.INTER_AREA)

    lines = [np.concatenate([thumb(i) for i in r], 1) for r in rows]
    w = min(x.shape[1] for x in lines)
    return np.concatenate([x[:, :w] for x in lines], 0)


def write_jpeg(path: Path, img: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80]):
            raise RuntimeError(f"{path}: could not write")


def avatar_info(clip: str, work: Path, dl: Dlib, regressor: str) -> dict:
    run, path = model_for(clip, work, regressor=regressor)
    seq, train, test = run_data(read_config(run))
    lm = np.asarray(seq.landmarks, np.float32)
    ref = mean_descriptor(dl, seq, train[np.linspace(0, len(train) - 1, 20).round().astype(int)], lm)
    own = [dl.faces(np.asarray(seq.frame(int(r))), box_of(lm[r]))["descriptor"]
           for r in test[np.linspace(0, len(test) - 1, min(30, len(test))).round().astype(int)]]
    own = [float(np.linalg.norm(d - ref)) for d in own if d is not None]
    still = Reenactor(path).avatar
    f = dl.faces(still.background, box_of(still.neutral))
    return {"path": path, "seq": seq, "train": train, "test": test, "ref": ref,
            "static_faces": f["n"], "static_identity": round(float(np.linalg.norm(f["descriptor"] - ref)), 3),
            "ring_scale": still.ring_scale,
            "own_heldout_identity_median": round(float(np.median(own)), 3), "own_heldout_identity_max": round(max(own), 3)}


def drive(info: dict, dl: Dlib, driver_lm: np.ndarray, neutral=None, real_rows=None, renderers=("static", "warp", "full"),
          sheet_rows=()) -> tuple[dict, dict]:
    """Figures per renderer and the sheet frames {row: {renderer: frame}}."""
    full = Reenactor(info["path"], neutral if neutral is not None else driver_neutral_of(driver_lm)[0])
    paste = Reenactor(info["path"], full.driver_neutral, full_frame=False) if "paste" in renderers else None
    # the still frame is one image: its detection figures are the avatar's (avatar_info)
    static_frame = full.avatar.background
    eyes = StillEyes(static_frame, full.avatar.neutral)
    still = ("static", "oracle", "warp_own")  # no detector figures: the still frame, the real face, the warp's bound
    tracks = {k: Track(None if k in still else dl, info["ref"], None if k in still else eyes) for k in renderers}
    shown = {}
    for i, lm in enumerate(driver_lm):
        out, a = full.step(lm)
        frames = {"full": out, "static": static_frame}
        if "warp" in renderers:
            frames["warp"] = full.frame_warp(a)
        if "warp_own" in renderers:
            frames["warp_own"] = full.frame_warp(lm)
        if paste is not None:
            frames["paste"] = paste.step(lm)[0]
        real = real_lm = None
        if real_rows is not None:
            real = np.asarray(info["seq"].frame(int(real_rows[i])))
            real_lm = info["seq"].landmarks[real_rows[i]]
        if "oracle" in renderers:
            _, masks, places = full.renderer.render(a[None])
            alpha = placed_alpha(masks[0, 0], places[0], real.shape[1::-1], full.feather)[..., None]
            frames["oracle"] = np.floor(alpha * real + (1.0 - alpha) * frames["warp"] + 0.5).astype(np.uint8)
        for k in renderers:
            tracks[k].add(frames[k], lm if k == "warp_own" else a, real, real_lm)
        if i in sheet_rows:
            shown[i] = frames
    return {k: t.summary() for k, t in tracks.items()}, shown


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/facesynth_th", help="where models are trained and exported")
    ap.add_argument("--sheets", help="directory for the contact sheets (JPEG)")
    ap.add_argument("--clips", default=",".join(CLIPS), help="self-reenactment clips")
    ap.add_argument("--pairs", default=",".join(f"{a}<-{d}" for a, d in PAIRS), help="cross pairs AVATAR<-DRIVER")
    ap.add_argument("--stride", type=int, default=1, help="every n-th driver frame of the cross pairs")
    ap.add_argument("--regressor", default="linear", help="the avatars' regressor (krr: the product's default)")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    dl = Dlib()
    out = {"load_average_start": load_average(), "regressor": args.regressor, "self": {}, "cross": {}, "sheets": []}
    infos = {}
    pairs = [tuple(p.split("<-")) for p in args.pairs.split(",") if p]
    for clip in dict.fromkeys([c for c in args.clips.split(",") if c] + [a for a, _ in pairs]):
        infos[clip] = avatar_info(clip, work, dl, args.regressor)
    sheet_for = {(a, d) for a, d in SHEET_PAIRS}
    for clip in [c for c in args.clips.split(",") if c]:
        info = infos[clip]
        test = info["test"]
        held = np.asarray(info["seq"].landmarks[test], np.float32)
        neutral = Reenactor(info["path"]).avatar.neutral
        rows = set(top_turns(held)) if (clip, clip) in sheet_for else set()
        figs, shown = drive(info, dl, held, neutral, real_rows=test, sheet_rows=rows,
                            renderers=("static", "warp", "full", "oracle", "warp_own"))
        figs.update({k: info[k] for k in ("own_heldout_identity_median", "static_faces", "static_identity", "ring_scale")})
        figs["frames"] = int(len(test))
        out["self"][clip] = figs
        if args.sheets and shown:
            img = sheet_image([[np.asarray(info["seq"].frame(int(test[i]))), shown[i]["static"], shown[i]["warp"],
                                shown[i]["full"]] for i in sorted(shown)])
            dest = Path(args.sheets) / f"talking_head_{clip}_self.jpg"
            write_jpeg(dest, img)
            out["sheets"].append(str(dest))
    for avatar, driver in pairs:
        drv = load_sequence(shared_clip(driver))
        lm = np.asarray(drv.landmarks, np.float32)[:: args.stride]
        rows = set(top_turns(lm)) if (avatar, driver) in sheet_for else set()
        figs, shown = drive(infos[avatar], dl, lm, renderers=("static", "warp", "full", "paste"), sheet_rows=rows)
        figs.update({k: infos[avatar][k] for k in ("own_heldout_identity_median", "static_faces", "static_identity",
                                                   "ring_scale")})
        out["cross"][f"{avatar}<-{driver}"] = figs
        if args.sheets and shown:
            img = sheet_image([[np.asarray(drv.frame(int(i * args.stride))), shown[i]["paste"], shown[i]["warp"],
                                shown[i]["full"]] for i in sorted(shown)])
            dest = Path(args.sheets) / f"talking_head_{avatar}_by_{driver}.jpg"
            write_jpeg(dest, img)
            out["sheets"].append(str(dest))
    out["load_average_end"] = load_average()
    out["wall_s"] = round(time.time() - t0, 1)
    emit(out)
if __name__ == "__main__":
    main()
