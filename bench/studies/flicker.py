"""Where the rendered face's flicker comes from, on trained runs; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.flicker RUN [RUN ...] [--min-cutoff 1.0 --beta 0.05]

Per run (a ``facesynth train`` run on video), on the evaluation's flicker frames
(:func:`facesynth.eval.flicker.flicker_rows`: 40 consecutive held-out frames), the face's mean
absolute frame-to-frame change pasted into the real frame (grey levels, 0-255; ``flicker``)
and its ratio to the real frames' for:

* ``sadm``: the prediction from the tracked landmarks, as the evaluation reports it;
* ``rewarp``: the real frame's own texture through the same landmarks (what the geometry
  and the warp alone add);
* ``sadm_mean_geometry``: the prediction from the tracked landmarks but held constant at the
  segment's mean texture prediction, warped on the tracked landmarks (the warp's share of the
  prediction's change);
* ``sadm_smooth``: the prediction and the warp from One Euro filtered landmarks
  (:func:`facesynth.runtime.filters.smooth_landmarks`, as ``facesynth app --smooth`` runs).

``real``: the real frames' own change. Also the landmarks' frame-to-frame motion (px, median
over points and frames) raw and filtered.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from facesynth.eval.common_region import common_landmarks
from facesynth.eval.flicker import flicker, flicker_rows
from facesynth.landmarks import get_scheme
from facesynth.rundir import read_config, run_data
from facesynth.runtime.filters import smooth_landmarks
from facesynth.sadm.fit import load_sadm


def predict(syn, lm: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return syn.texture(torch.from_numpy(np.asarray(lm, np.float32))).reshape(len(lm), -1).numpy()


def one(run: Path, min_cutoff: float, beta: float) -> dict:
    sadm = load_sadm(run)
    cfg = read_config(run)
    cfg.data.smooth_landmarks = False  # the landmarks as tracked (this study's starting point)
    seq, _, te = run_data(cfg)
    model, syn = sadm.model, sadm.synthesizer()
    rows = te[flicker_rows(len(te), 40)]
    common = common_landmarks(seq, None)[rows]
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    raw = seq.landmarks[rows]
    meta = Path(str(cfg.data.path)) / "meta.json"
    fps = float(json.loads(meta.read_text())["video"]["fps"]) if meta.is_file() else 25.0
    fps /= max(1.0, float(np.median(np.diff(seq.frame_index[rows]))))  # the rows' own rate (subsampled clips)
    smooth = smooth_landmarks(raw, fps, min_cutoff, beta).astype(np.float32)
    pred = predict(syn, raw)
    texs = {"sadm": pred, "rewarp": model.sample_textures(model_seq, rows),
            "sadm_mean_geometry": np.repeat(pred.mean(0, keepdims=True), len(rows), 0)}
    out = flicker(model, texs, seq, rows, common, 2.0)
    seq_smooth = seq.with_landmarks(smooth) if hasattr(seq, "with_landmarks") else None
    if seq_smooth is None:  # render on the filtered landmarks: a sequence view whose landmarks are replaced
        import copy

        seq_smooth = copy.copy(seq)
        lm_all = seq.landmarks.copy()
        lm_all[rows] = smooth
        seq_smooth.landmarks = lm_all
    fs = flicker(model, {"sadm_smooth": predict(syn, smooth)}, seq_smooth, rows, common, 2.0)
    out["sadm_smooth"], out["ratio"]["sadm_smooth"] = fs["sadm_smooth"], fs["ratio"]["sadm_smooth"]
    motion = {name: float(np.median(np.linalg.norm(np.diff(x, axis=0), axis=-1))) for name, x in (("raw", raw), ("smooth", smooth))}
    return {"fps": fps, "flicker": {k: v for k, v in out.items() if k not in ("ratio", "frames")}, "ratio": out["ratio"],
            "frames": out["frames"], "landmark_motion_px": motion}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--min-cutoff", type=float, default=1.0)
    ap.add_argument("--beta", type=float, default=0.05)
    args = ap.parse_args()
    result = {}
    for run in args.runs:
        result[run.name] = one(run, args.min_cutoff, args.beta)
        print(json.dumps({"run": run.name, **result[run.name]}), file=sys.stderr, flush=True)
    print(json.dumps({"bench": "flicker", "min_cutoff": args.min_cutoff, "beta": args.beta, "runs": result}))


if __name__ == "__main__":
    main()
