"""The example-based detail (``model.detail``) along its strength, on trained runs; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.detail RUN [RUN ...] [--detail 0,0.25,0.5,0.75,1] \
        [--set detail_parts=mouth --set detail_k=4] [--today DIR] [--jobs 2]

Each RUN is a ``facesynth train`` run (video data). Its face model gets a detail bank fitted on
the run's own training frames (:func:`facesynth.model.detail.fit_detail_bank`, the settings of
``--set`` over the run's), exactly as training with ``model.detail > 0`` fits it, and the run
is evaluated held out (sigma 0, the face pasted into the real frame, as ``bench/studies/perceptual.py``
reports it) at every strength of ``--detail`` (0 = the run as trained, without the bank). Per
run and strength, one line on stderr with ``lpips_face``, ``lpips_eyes``, ``lpips_mouth``,
``psnr_frame_common``, ``sharpness``, ``flicker_ratio``; the bank's size and fit seconds. The
strength 0 is read from the run's own ``metrics.json`` when it holds these figures (the
evaluation of training), else evaluated. The last line (stdout) holds them all, and with
``--today DIR`` (``DIR/CLIP__today``: the runs of today's default, as ``bench/studies/perceptual.py
--out DIR`` leaves them; a run folder is named ``CLIP__VARIANT``) the issue's acceptance per
strength against today's figures (``bench.studies.perceptual.summary``).

``--smoothed``: the bank fitted and the runs evaluated on landmarks smoothed as
``data.smooth_landmarks=true`` does (:func:`bench.studies.landmark_smoothing.run_sequence`),
whatever the runs were trained on; strength 0 is then evaluated too. ``--today-json FILE``:
today's figures from a ``bench.studies.landmark_smoothing`` line (its ``CLIP__today`` runs), on
their landmarks as tracked (today's default when #44 was written: the study's baseline) or, with
``--today-smoothed``, smoothed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.studies.landmark_smoothing import run_sequence
from bench.studies.perceptual import against_today
from bench.studies.perceptual import metric_figures as figures
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.landmarks import get_scheme
from facesynth.model.detail import fit_detail_bank
from facesynth.rundir import read_config, run_data
from facesynth.sadm.fit import load_sadm


def attach_bank(sadm, seq, tr, settings: dict, strength: float = 1.0) -> dict:
    """Fit the detail bank of ``sadm``'s face model on the training rows ``tr`` of ``seq`` (as
    training with ``model.detail > 0`` does) and set its strength; returns the bank's report."""
    model = sadm.model
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    model.config = dataclasses.replace(model.config, **settings, detail=1.0)
    t0 = time.perf_counter()
    tex_tr = model.sample_textures(model_seq, tr)
    t1 = time.perf_counter()
    model.detail_bank, bank = fit_detail_bank(model, model_seq.landmarks[tr], tex_tr)
    bank["seconds"] = time.perf_counter() - t1
    bank["texture_seconds"] = t1 - t0
    model.config = dataclasses.replace(model.config, detail=float(strength))
    return bank


def sweep(run: Path, strengths: list[float], settings: dict, frames: int | None = None, smoothed: bool = False) -> dict:
    sadm = load_sadm(run)
    if smoothed:  # the landmarks smoothed as data.smooth_landmarks=true does, whatever the run had
        cfg, seq, tr, te, _ = run_sequence(run, True)
    else:
        cfg = read_config(run)
        seq, tr, te = run_data(cfg)
    model = sadm.model
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    bank = attach_bank(sadm, seq, tr, settings)
    ecfg = EvalConfig(noise=[0.0], train_level=False, talking_head=False)
    if frames:
        ecfg.max_test_frames = frames
    common = common_landmarks(seq, None)
    tex_te = model.sample_textures(model_seq, te)
    out = {}
    if 0 in strengths and not smoothed and (run / "metrics.json").is_file():
        m = json.loads((run / "metrics.json").read_text())
        if "lpips_frame_common" in m and "flicker_frame_common" in m:
            out["0.0"] = figures(m)
            print(json.dumps({"run": run.name, "detail": 0.0, **out["0.0"]}), file=sys.stderr, flush=True)
    for s in strengths:
        if str(float(s)) in out:
            continue
        model.config = dataclasses.replace(model.config, detail=float(s))
        metrics, _ = evaluate_sadm(sadm, seq, tr, te, ecfg, int(cfg.seed), test_textures=tex_te, common=common)
        out[str(float(s))] = figures(metrics)
        print(json.dumps({"run": run.name, "detail": s, **out[str(float(s))]}), file=sys.stderr, flush=True)
    return {"bank": bank, "settings": {k: getattr(model.config, k) for k in ("detail_k", "detail_parts", "detail_sigma",
                                                                                "detail_band", "detail_blend", "detail_feather",
                                                                                "detail_reach")},
            "reference_width": model.reference.size[1], "strengths": out}


def plot(result: dict, path: Path) -> None:
    """Per run: face and mouth LPIPS relative to strength 0, and the PSNR change (dB), along the strength."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4))
    for name, r in sorted(result.items()):
        st = sorted(r["strengths"], key=float)
        x = [float(v) for v in st]
        f0 = r["strengths"][st[0]]
        for ax, key in zip(axes[:2], ("lpips_face", "lpips_mouth"), strict=True):
            ax.plot(x, [r["strengths"][v][key] / f0[key] for v in st], "o-", label=name.split("__")[0])
        axes[2].plot(x, [r["strengths"][v]["psnr_frame_common"] - f0["psnr_frame_common"] for v in st], "o-")
    for ax, t in zip(axes, ("face LPIPS / at detail 0", "mouth LPIPS / at detail 0", "psnr_frame_common change (dB)"),
                     strict=True):
        ax.set_xlabel("model.detail")
        ax.set_title(t, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def parse_settings(pairs: list[str]) -> dict:
    """``KEY=VALUE`` strings of ``model.detail_*`` settings -> their typed values."""
    settings = {}
    for kv in pairs:
        k, _, v = kv.partition("=")
        settings[k] = v if k in ("detail_parts", "detail_band", "detail_blend") else (int(v) if k == "detail_k" else float(v))
    return settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--detail", default="0,0.25,0.5,0.75,1", help="strengths, comma-separated")
    ap.add_argument("--frames", type=int, default=None, help="frame-level test frames (default: EvalConfig's)")
    ap.add_argument("--today", type=Path, default=None, help="folder of today's runs, CLIP__today")
    ap.add_argument("--plot", type=Path, default=None, help="write the face and mouth LPIPS and the PSNR along the strength (PNG)")
    ap.add_argument("--from-json", type=Path, default=None, help="plot/summarise a previous run's stdout line instead of measuring")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (default 1)")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE of model.detail_* (repeatable)")
    ap.add_argument("--smoothed", action="store_true",
                    help="evaluate (and fit the bank) on landmarks smoothed as data.smooth_landmarks=true does, "
                         "whatever the runs were trained on")
    ap.add_argument("--today-json", type=Path, default=None,
                    help="today's figures from a bench.studies.landmark_smoothing line (its CLIP__today runs, "
                         "tracked unless --today-smoothed) instead of --today's metrics.json")
    ap.add_argument("--today-smoothed", action="store_true", help="--today-json's figures on smoothed landmarks")
    args = ap.parse_args()
    strengths = [float(v) for v in args.detail.split(",") if v.strip()]
    settings = parse_settings(args.set)
    result = {}

    def one(run):
        r = sweep(run, strengths, settings, args.frames, args.smoothed)
        print(json.dumps({"run": run.name, "bank": r["bank"]}), file=sys.stderr, flush=True)
        return run.name, r

    if args.from_json is not None:
        result = json.loads(args.from_json.read_text().strip().splitlines()[-1])["runs"]
    else:
        with ThreadPoolExecutor(args.jobs) as ex:
            result = dict(ex.map(one, args.runs))
    if args.plot is not None:
        plot(result, args.plot)
    today = args.today
    if args.today_json is not None:
        mode = "smoothed" if args.today_smoothed else "tracked"
        line = json.loads(args.today_json.read_text().strip().splitlines()[-1])
        today = {name.split("__")[0]: r[mode] for name, r in line["runs"].items() if name.endswith("__today") and mode in r}
    acceptance = (against_today(today, {n: {f"detail={k}": v for k, v in r["strengths"].items()} for n, r in result.items()})
                  if today else {})
    print(json.dumps({"bench": "detail", "settings": settings, "smoothed": args.smoothed, "runs": result,
                      "acceptance": acceptance}))


if __name__ == "__main__":
    main()
