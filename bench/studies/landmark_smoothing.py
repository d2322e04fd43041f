"""Held-out figures of trained runs with the landmarks as tracked and zero-phase smoothed; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.landmark_smoothing RUN [RUN ...] [--cache DIR]

Each RUN (a ``facesynth train`` run on a shared clip) is evaluated twice on its held-out
frames (temporal split, sigma 0, the evaluation of ``bench.studies.perceptual``:
``eval.noise=[0]``, no training-level or talking-head rows): ``tracked``, the test landmarks
as the tracker gave them, and ``smoothed``, the test landmarks smoothed as
``data.smooth_landmarks=true`` does (:mod:`facesynth.data.smoothing`, the test part alone).
The model is the run's own: a run trained with ``data.smooth_landmarks=true`` learnt from
smoothed training landmarks (``trained_smoothed``). Per evaluation, as the perceptual bench
reports them: ``flicker_ratio`` (``flicker_frame_common``), ``psnr_frame_common`` (dB),
``lpips_face`` / ``lpips_mouth`` / ``lpips_eyes`` (median over frames), ``sharpness``; and the
test landmarks' frame-to-frame motion (px, median over points and the flicker frames) and
the inner mouth opening's largest value (points 62-66, px) over the test part; smoothed:
``smoothing_s``, the smoothing's own time on the run's whole clip (median of 5).

``summary``: over the runs evaluated both ways, the largest flicker ratio each way, the
smallest PSNR change and the largest relative LPIPS changes (face, mouth).

``--fast-radii-s X``: the smoothed evaluation with another motion threshold (the filter's
trade-off between still and fast-moving clips; cached apart). ``--light-shift-px D``: with
another limit on the light filter's move of the face's centroid (``none``: no limit, the filter
before the limit; cached apart).

``--plot FILE``: a tracked and a smoothed track (lp_d19's chin, vrt_face2's lower inner lip).

``--cache DIR``: keep each evaluation's figures in DIR (``<run name>__tracked.json``,
``<run name>__smoothed_<threshold>[_shift<limit>].json``, no suffix without a limit) and reuse
them, so the table is printed again without re-evaluating.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.harness import emit, host, load
from bench.studies.perceptual import metric_figures
from facesynth.data.smoothing import FAST_RADII_S, LIGHT_SHIFT_PX, smooth_sequence, split_bounds
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.flicker import flicker_rows
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.rundir import read_config, run_data
from facesynth.sadm.fit import load_sadm

MODES = {"tracked": False, "smoothed": True}


def run_sequence(run: Path, smoothed: bool, fast_radii_s: float = FAST_RADII_S,
                 light_shift_px: float | None = LIGHT_SHIFT_PX):
    """A run's config, sequence, split (train rows, test rows) and whether it was trained on
    smoothed landmarks; the sequence's landmarks as tracked, or (``smoothed``) smoothed as
    ``data.smooth_landmarks=true`` does, each part of the split alone, with these settings
    (the defaults', not the run's)."""
    cfg = read_config(run)
    trained_smoothed = bool(cfg.data.smooth_landmarks)
    cfg.data.smooth_landmarks = False
    seq, tr, te = run_data(cfg)
    if smoothed:  # as data.smooth_landmarks=true does (load_data), with this motion threshold
        bounds = split_bounds(len(seq), float(cfg.data.train_fraction), int(cfg.data.gap))
        seq = smooth_sequence(seq, bounds, fast_radii_s=fast_radii_s, light_shift_px=light_shift_px)
    return cfg, seq, tr, te, trained_smoothed


def evaluate(run: Path, smoothed: bool, fast_radii_s: float = FAST_RADII_S, light_shift_px: float | None = LIGHT_SHIFT_PX) -> dict:
    cfg, seq, tr, te, trained_smoothed = run_sequence(run, smoothed, fast_radii_s, light_shift_px)
    bounds = split_bounds(len(seq), float(cfg.data.train_fraction), int(cfg.data.gap))
    ecfg = EvalConfig(noise=[0.0], train_level=False, talking_head=False,
                      flicker_frames=int(cfg.eval.get("flicker_frames", 40)))
    common = common_landmarks(seq, None)
    metrics, _ = evaluate_sadm(load_sadm(run), seq, tr, te, ecfg, int(cfg.seed), common=common)
    lm = seq.landmarks[te]
    if smoothed:  # what the smoothing itself costs on this clip (median of 5, seconds)
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            smooth_sequence(seq, bounds, fast_radii_s=fast_radii_s, light_shift_px=light_shift_px)
            times.append(time.perf_counter() - t0)
        extra = {"smoothing_s": float(np.median(times)), "frames": len(seq)}
    else:
        extra = {}
    fl = lm[flicker_rows(len(te), ecfg.flicker_frames)]
    return {**metric_figures(metrics), "trained_smoothed": trained_smoothed,
            "landmark_motion_px": float(np.median(np.linalg.norm(np.diff(fl, axis=0), axis=-1))),
            "mouth_open_max_px": float(np.linalg.norm(lm[:, 66] - lm[:, 62], axis=-1).max()), **extra}


def summary(runs: dict) -> dict:
    """Over the runs evaluated both ways: the largest flicker ratio each way, the smallest
    PSNR change (dB) and the largest relative LPIPS changes (face, mouth) from tracked to smoothed."""
    both = [r for r in runs.values() if "tracked" in r and "smoothed" in r]
    if not both:
        return {}

    def rel(key):
        return max(r["smoothed"][key] / r["tracked"][key] - 1 for r in both if r["tracked"][key])

    return {"runs": len(both), "flicker_ratio_max_tracked": max(r["tracked"]["flicker_ratio"] for r in both),
            "flicker_ratio_max_smoothed": max(r["smoothed"]["flicker_ratio"] for r in both),
            "psnr_change_min_db": min(r["smoothed"]["psnr_frame_common"] - r["tracked"]["psnr_frame_common"] for r in both),
            "lpips_face_change_max": rel("lpips_face"), "lpips_mouth_change_max": rel("lpips_mouth")}


def plot(path: Path) -> None:
    """The tracked and smoothed track of a still clip's chin (lp_d19) and a talking clip's lower
    inner lip (vrt_face2), the first 3 s of their training parts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from facesynth.data import load_sequence, shared_clip
    from facesynth.data.smoothing import smooth_track, split_bounds

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.2), dpi=90)
    for ax, (clip, point, what) in zip(axes, [("lp_d19", 8, "chin (point 8)"), ("vrt_face2", 66, "lower inner lip (point 66)")],
                                       strict=True):
        seq = load_sequence(shared_clip(clip))
        train = seq.landmarks[:split_bounds(len(seq), 0.75, 0)[0]]
        smooth = smooth_track(train, seq.fps)
        n = min(len(train), int(3 * seq.fps))
        t = np.arange(n) / seq.fps
        ax.plot(t, train[:n, point, 1], ".-", color="0.6", lw=0.8, ms=3, label="tracked (dlib)")
        ax.plot(t, smooth[:n, point, 1], "-", color="C3", lw=1.5, label="data.smooth_landmarks")
        ax.set_title(f"{clip}: {what}, y", fontsize=9)
        ax.set_xlabel("s")
        ax.set_ylabel("px")
        ax.invert_yaxis()
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--plot", type=Path, help="also draw a tracked and a smoothed track (PNG) here")
    ap.add_argument("--cache", type=Path, help="keep and reuse each evaluation's figures here")
    ap.add_argument("--modes", default="tracked,smoothed", help="comma-separated: tracked, smoothed")
    ap.add_argument("--fast-radii-s", type=float, default=FAST_RADII_S,
                    help=f"the smoothing's motion threshold, face radii/s (default {FAST_RADII_S}, data.smooth_landmarks')")
    ap.add_argument("--light-shift-px", type=lambda v: None if v.lower() == "none" else float(v), default=LIGHT_SHIFT_PX,
                    help=f"the most the light filter moves the face's centroid, px, or none (default {LIGHT_SHIFT_PX}, "
                         "data.smooth_light_shift_px')")
    args = ap.parse_args()
    if args.plot:
        plot(args.plot)
    modes = [m for m in args.modes.split(",") if m]
    bad = [m for m in modes if m not in MODES]
    if bad:
        sys.exit(f"landmark_smoothing: unknown mode(s) {bad} (known: {', '.join(MODES)})")
    if args.cache:
        args.cache.mkdir(parents=True, exist_ok=True)
    out, runs = {"bench": "landmark_smoothing", **host()}, {}
    with load() as around:
        for run in args.runs:
            runs[run.name] = {}
            for mode in modes:
                shift = "" if args.light_shift_px is None else f"_shift{args.light_shift_px:g}"
                tag = mode if mode == "tracked" else f"{mode}_{args.fast_radii_s:g}{shift}"  # the settings in the name
                cached = args.cache / f"{run.name}__{tag}.json" if args.cache else None
                if cached is not None and cached.is_file():
                    fig = json.loads(cached.read_text())
                else:
                    fig = evaluate(run, MODES[mode], args.fast_radii_s, args.light_shift_px)
                    if cached is not None:
                        cached.write_text(json.dumps(fig))
                runs[run.name][mode] = fig
                print(json.dumps({"run": run.name, "mode": mode, **fig}), file=sys.stderr, flush=True)
    emit({**out, "fast_radii_s": args.fast_radii_s, "light_shift_px": args.light_shift_px, "runs": runs, "summary": summary(runs),
          "load": around})


if __name__ == "__main__":
    main()
