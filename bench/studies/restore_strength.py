"""The restoration filter's strength chosen on held-out predictions, on trained runs; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.restore_strength RUN [RUN ...] [--guard 0.05] \
        [--variants guarded,full,none] [--jobs 2] [--today DIR]

Each RUN is a ``facesynth train`` run with ``model.restore=true`` trained before the strength
was chosen (its filter at full strength). The strength is chosen as ``facesynth train`` now
chooses it (:func:`facesynth.model.restore.guard_restoration`: the SADM refitted without its
shrinkage on the training rows before the validation slice and a gap as long, the slice's
predictions pasted into their real frames, the largest strength whose PSNR cost there is at
most ``--guard`` dB), and the run is evaluated held out (sigma 0, the face pasted into the real
frame, the figures of ``bench/studies/perceptual.py``) with the filter ``guarded`` (at that
strength), ``full`` (as trained) or ``none``. Per run, lines on stderr; the last line (stdout)
holds them all and, with ``--today DIR`` (``DIR/CLIP__today``), the acceptance per variant.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

from bench.studies.perceptual import against_today
from bench.studies.perceptual import metric_figures as figures
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.landmarks import get_scheme
from facesynth.model.restore import guard_restoration
from facesynth.rundir import read_config, run_data
from facesynth.sadm.fit import fit_sadm, load_sadm


def study(run: Path, guard: float, variants: list[str]) -> dict:
    sadm = load_sadm(run)
    cfg = read_config(run)
    seq, tr, te = run_data(cfg)
    model = sadm.model
    kernel = model.restore_kernel
    if kernel is None:
        raise SystemExit(f"{run}: no restoration filter (train with model.restore=true)")
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    t0 = time.perf_counter()
    model.restore_kernel = None
    tex_tr = model.sample_textures(model_seq, tr)
    model.restore_kernel = kernel
    n_val = int(round(len(tr) * sadm.config.val_fraction))
    params = {k: v for k, v in sadm.regressor_config.items() if k != "info"}  # info: what the fit found
    probe = replace(sadm.config, region_shrink=False, search=False, gaze_folds=0, restore_guard=None)

    def refit(i):  # as fit_sadm refits it
        return fit_sadm(model, seq, tr[i], tex_tr[i], sadm.name, params, probe, int(cfg.seed)).synthesizer()

    report = guard_restoration(refit, model, seq, tr, n_val, guard)
    kernels = {"guarded": model.restore_kernel, "full": kernel, "none": None}
    out = {**report, "guard_seconds": time.perf_counter() - t0, "variants": {}}
    print(json.dumps({"run": run.name, **{k: v for k, v in report.items() if k != "curve_db"}}), file=sys.stderr, flush=True)
    ecfg = EvalConfig(noise=[0.0], train_level=False, talking_head=False)
    common = common_landmarks(seq, None)
    model.restore_kernel = None
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
    ap.add_argument("--variants", default="guarded", help="comma-separated: guarded, full, none")
    ap.add_argument("--today", type=Path, default=None, help="folder of today's runs, CLIP__today")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    with ThreadPoolExecutor(args.jobs) as ex:
        result = dict(zip((r.name for r in args.runs), ex.map(lambda r: study(r, args.guard, variants), args.runs),
                          strict=True))
    acceptance = against_today(args.today, {n: r["variants"] for n, r in result.items()}) if args.today else {}
    print(json.dumps({"bench": "restore_strength", "guard_db": args.guard, "runs": result, "acceptance": acceptance}))


if __name__ == "__main__":
    main()
