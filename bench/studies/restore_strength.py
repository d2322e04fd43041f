"""The restoration filter's strength chosen on held-out predictions, on trained runs; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.restore_strength RUN [RUN ...] [--guard 0.05] [--jobs 2] \
        [--today DIR]

Each RUN is a ``facesynth train`` run with ``model.restore=true``. The run's SADM is refitted
(without its region shrinkage) on the first ``1 - sadm.val_fraction`` of the training frames and
predicts the rest (the validation slice, the training frames nearest the test segment in time);
:func:`facesynth.model.restore.strength_curve` gives the PSNR change of those predictions, pasted
into their real frames, along the filter's strength ``s`` (``K_s = delta + s (K - delta)``), and
:func:`~facesynth.model.restore.choose_strength` the largest strength within ``--guard`` dB. The
run is evaluated held out (sigma 0, the face pasted into the real frame, the figures of
``bench/studies/perceptual.py``) with: ``guarded`` (K at the chosen strength) and ``fitted_on_val``
(a kernel fitted by :func:`~facesynth.model.restore.fit_restoration` on the predictions
themselves instead of on the frames' own textures). Per run, a line on stderr; the last line
(stdout) holds them all and, with ``--today DIR`` (``DIR/CLIP__today``), the acceptance per variant.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bench.studies.perceptual import figures as run_figures
from bench.studies.perceptual import metric_figures as figures
from bench.studies.perceptual import summary
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.landmarks import get_scheme
from facesynth.model.restore import STRENGTHS, choose_strength, fit_restoration, strength_curve, with_strength
from facesynth.rundir import read_config, run_data
from facesynth.sadm.fit import fit_sadm, load_sadm


def held_out_predictions(sadm, seq, tr, tex_tr, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(validation rows, their textures predicted by the SADM refitted without them)."""
    n_val = max(2, int(round(len(tr) * sadm.config.val_fraction)))
    probe_cfg = replace(sadm.config, region_shrink=False, search=False, gaze_folds=0)
    params = {k: v for k, v in sadm.regressor_config.items() if k != "info"}  # info: what the fit found, not a setting
    probe = fit_sadm(sadm.model, seq, tr[:-n_val], tex_tr[:-n_val], sadm.name, params, probe_cfg, seed)
    val = tr[-n_val:]
    with torch.no_grad():
        pred = probe.synthesizer().texture(torch.from_numpy(seq.landmarks[val]))
    return val, pred.reshape(len(val), -1).numpy()


def study(run: Path, guard: float, variants: list[str]) -> dict:
    sadm = load_sadm(run)
    cfg = read_config(run)
    seq, tr, te = run_data(cfg)
    model = sadm.model
    kernel = model.restore_kernel
    if kernel is None:
        raise SystemExit(f"{run}: no restoration filter (train with model.restore=true)")
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    model.restore_kernel = None
    t0 = time.perf_counter()
    tex_tr = model.sample_textures(model_seq, tr)
    val, pred = held_out_predictions(sadm, seq, tr, tex_tr, int(cfg.seed))
    t1 = time.perf_counter()
    curve = strength_curve(model, model_seq, val, pred, kernel)
    strength = choose_strength(curve, STRENGTHS, guard)
    t2 = time.perf_counter()
    kernels = {"guarded": with_strength(kernel, strength)}
    if "fitted_on_val" in variants:
        kernels["fitted_on_val"], _ = fit_restoration(model, model_seq, val, pred)
    out = {"strength": strength, "curve": {f"{s:.3f}": float(c) for s, c in zip(STRENGTHS, curve, strict=True)},
           "val_frames": int(len(val)), "predict_s": t1 - t0, "curve_s": t2 - t1, "variants": {}}
    print(json.dumps({"run": run.name, "strength": strength, "curve_at_1": float(curve[-1])}), file=sys.stderr, flush=True)
    ecfg = EvalConfig(noise=[0.0], train_level=False, talking_head=False)
    common = common_landmarks(seq, None)
    tex_te = model.sample_textures(model_seq, te)
    for name in variants:
        model.restore_kernel = kernels[name]
        metrics, _ = evaluate_sadm(sadm, seq, tr, te, ecfg, int(cfg.seed), test_textures=tex_te, common=common)
        out["variants"][name] = figures(metrics)
        print(json.dumps({"run": run.name, "variant": name, **out["variants"][name]}), file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--guard", type=float, default=0.05, help="PSNR loss (dB) allowed on the validation predictions")
    ap.add_argument("--variants", default="guarded", help="comma-separated: guarded, fitted_on_val")
    ap.add_argument("--today", type=Path, default=None, help="folder of today's runs, CLIP__today")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    with ThreadPoolExecutor(args.jobs) as ex:
        result = dict(zip((r.name for r in args.runs), ex.map(lambda r: study(r, args.guard, variants), args.runs),
                          strict=True))
    acceptance = {}
    if args.today is not None:
        per_clip = {}
        for name, r in result.items():
            clip = name.split("__")[0]
            today = args.today / f"{clip}__today"
            if (today / "metrics.json").is_file():
                per_clip[clip] = {"today": run_figures(today), **r["variants"]}
        acceptance = {v: summary(per_clip, v) for v in variants}
    print(json.dumps({"bench": "restore_strength", "guard_db": args.guard, "runs": result, "acceptance": acceptance}))


if __name__ == "__main__":
    main()
