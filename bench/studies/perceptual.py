"""Issue 44's yardstick per shared clip, for today's default and variants; prints one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.perceptual [--clips lp_d3,lp_d20] \
        [--variant auto=model.reference_width=auto] [--jobs 2] [--out DIR]

Each clip (default: every clip of ../shared/data/faces) is trained with ``facesynth train
data=video data.path=CLIP`` (temporal split 75/25, default configuration; the evaluation
restricted to what is reported: ``eval.noise=[0] eval.train_level=false
eval.talking_head=false``, which leaves the sigma-0 figures unchanged) once per variant:
``today`` (no override) and each ``--variant NAME=OVERRIDE[,OVERRIDE...]``. Per clip and
variant, held out, sigma 0, row ``sadm``, the face pasted into the real frame:

* ``lpips_face``, ``lpips_eyes``, ``lpips_mouth``: LPIPS-Alex, median over the 100 evaluated
  frames (``lpips_frame_common``; needs the ``perceptual`` extra);
* ``psnr_frame_common`` (dB), ``sharpness`` (the whole common region's, ``sharpness_frame_common``);
* ``flicker_ratio``: the face's frame-to-frame change over the real frames' (``flicker_frame_common``);
* ``lpips_ceiling``: per part (face, eyes, mouth), the LPIPS of the ``oracle`` (the frame's own
  texture projected on the appearance PCA) and of the ``rewarp`` (that texture through the render
  path): what a perfect regressor and a perfect appearance model would reach;
* ``train_s``: face model + SADM fit seconds (``timings_s``; the width guard's fits included),
  ``model_mb``: the run's model files;
* ``width_px``: the reference width trained (``auto`` resolved, or the width guard's choice), and
  ``width_guard``: the guard's report (``metrics.json``; None when off).

The summary holds, per variant against ``today``, the issue's acceptance: the median over
clips of the per-clip relative LPIPS change (face, mouth), the clips whose face LPIPS did not
drop, the worst per-clip PSNR change, the sharpness median and maximum, and the largest
flicker ratio; beside them ``ceiling_change_median``: the same median change of the variant's
oracle and re-warp per part, against today's prediction. Runs go into ``--out`` (default: a temporary folder, removed).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.harness import emit  # noqa: E402
from facesynth.data.shared import shared_data_dir  # noqa: E402

EVAL = ["eval.noise=[0]", "eval.train_level=false", "eval.talking_head=false"]


PARTS, CEILINGS = ("face", "eyes", "mouth"), ("oracle", "rewarp")


def metric_figures(m: dict) -> dict:
    """The acceptance figures of one run's metrics (held out, sigma 0, the prediction's row)."""
    lp = m.get("lpips_frame_common") or {}
    return {
        "lpips_face": lp.get("face", {}).get("sadm"), "lpips_eyes": lp.get("eyes", {}).get("sadm"),
        "lpips_mouth": lp.get("mouth", {}).get("sadm"),
        "psnr_frame_common": m["psnr_frame_common"]["sadm"]["0"],
        "sharpness": m["sharpness_frame_common"]["whole"]["sadm"],
        "flicker_ratio": m["flicker_frame_common"]["ratio"]["sadm"],
        "lpips_ceiling": {part: {row: lp.get(part, {}).get(row) for row in CEILINGS} for part in PARTS},
    }


def figures(run: Path) -> dict:
    m = json.loads((run / "metrics.json").read_text())
    size = sum(f.stat().st_size for sub in ("face_model", "sadm") for f in (run / sub).rglob("*") if f.is_file())
    return {
        **metric_figures(m),
        "reference_width": m["config"]["model"]["reference_width"],
        "width_px": json.loads((run / "face_model" / "face_model.json").read_text())["config"]["reference_width"],
        "width_guard": m.get("width_guard"),  # model.width_guard's choice and validation figures (None: off)
        "n_appearance": m["n_appearance"],
        "train_s": m["timings_s"]["face_model"] + m["timings_s"]["sadm_fit"],
        "model_mb": size / 1e6,
    }


def train(clip: Path, overrides: list[str], run: Path) -> dict:
    cmd = [sys.executable, "-m", "facesynth", "train", "data=video", f"data.path={clip}", f"hydra.run.dir={run}", *EVAL,
           *overrides]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"{clip.name} {overrides}: exit {p.returncode}: {p.stderr.strip().splitlines()[-1:]}")
    return figures(run)


def summary(per_clip: dict, name: str) -> dict:
    base, new = [], []
    for fig in per_clip.values():
        if "today" in fig and name in fig:
            base.append(fig["today"])
            new.append(fig[name])
    if not base:
        return {}

    def rel(key):
        return [n[key] / b[key] - 1 for b, n in zip(base, new, strict=True) if b[key] and n[key] is not None]

    face, mouth = rel("lpips_face"), rel("lpips_mouth")
    dpsnr = [n["psnr_frame_common"] - b["psnr_frame_common"] for b, n in zip(base, new, strict=True)]
    sharp = [n["sharpness"] for n in new]

    def ceiling(part, row):
        ch = [n["lpips_ceiling"][part][row] / b[f"lpips_{part}"] - 1 for b, n in zip(base, new, strict=True)
              if b.get(f"lpips_{part}") and (n.get("lpips_ceiling") or {}).get(part, {}).get(row) is not None]
        return float(np.median(ch)) if ch else None

    return {"clips": len(base), "lpips_face_change_median": float(np.median(face)) if face else None,
            "lpips_face_not_lower": int(sum(v >= 0 for v in face)),
            "lpips_mouth_change_median": float(np.median(mouth)) if mouth else None,
            "psnr_change_min_db": float(min(dpsnr)), "sharpness_median": float(np.median(sharp)),
            "sharpness_max": float(max(sharp)), "flicker_ratio_max": float(max(n["flicker_ratio"] for n in new)),
            "ceiling_change_median": {p: {r: ceiling(p, r) for r in CEILINGS} for p in PARTS}}


def against_today(today: Path | dict[str, dict], runs: dict[str, dict]) -> dict:
    """The acceptance (:func:`summary`) of each variant against today's run of the same clip:
    ``runs`` maps a run folder's name (``CLIP__VARIANT``) to ``{variant: figures}``; today's
    figures come from ``today/CLIP__today``, or from ``today`` itself when it maps a clip to
    them; clips without them are left out."""
    per_clip = {}
    for name, variants in runs.items():
        clip = name.split("__")[0]
        if isinstance(today, dict):
            if clip in today:
                per_clip[clip] = {"today": today[clip], **variants}
        elif (today / f"{clip}__today" / "metrics.json").is_file():
            per_clip[clip] = {"today": figures(today / f"{clip}__today"), **variants}
    names = sorted({n for fig in per_clip.values() for n in fig if n != "today"})
    return {n: summary(per_clip, n) for n in names}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", default="", help="comma-separated shared clip names (default: all)")
    ap.add_argument("--variant", action="append", default=[], help="NAME=OVERRIDE[,OVERRIDE...] (repeatable)")
    ap.add_argument("--no-today", action="store_true", help="leave today's default out (figures of the variants only)")
    ap.add_argument("--jobs", type=int, default=1, help="trainings at once (default 1)")
    ap.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    args = ap.parse_args()
    faces = shared_data_dir() / "faces" if shared_data_dir() else None
    if faces is None or not faces.is_dir():
        sys.exit("bench_perceptual: ../shared/data/faces is absent")
    clips = [faces / c for c in args.clips.split(",")] if args.clips else sorted(p for p in faces.iterdir() if p.is_dir())
    variants = {} if args.no_today else {"today": []}
    for v in args.variant:
        name, _, ov = v.partition("=")
        variants[name] = [o for o in ov.split(",") if o]
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        jobs = [(c, n, ov) for c in clips for n, ov in variants.items()]  # interleaved: one clip's variants together
        per_clip: dict = {c.name: {} for c in clips}

        def one(job):
            c, n, ov = job
            run = out / f"{c.name}__{n}"
            fig = figures(run) if (run / "metrics.json").is_file() and args.out else train(c, ov, run)
            print(json.dumps({"clip": c.name, "variant": n, **fig}), file=sys.stderr, flush=True)
            return c.name, n, fig

        with ThreadPoolExecutor(args.jobs) as ex:
            for c, n, fig in ex.map(one, jobs):
                per_clip[c][n] = fig
    result = {"bench": "perceptual", "variants": variants, "eval": EVAL, "clips": per_clip,
              "summary": {n: summary(per_clip, n) for n in variants if n != "today"}}
    emit(result)
if __name__ == "__main__":
    main()
