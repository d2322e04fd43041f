"""Does a validation slice predict the test frames' PSNR cost of a wider reference frame? One JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.width_guard [--clips vrt_face5,lp_d13]

Per shared clip (default configuration, temporal split 75/25, ``data.smooth_landmarks`` as the
default has it), at 128 px and at ``model.reference_width=auto``, without the restoration filter:
the face model and the SADM (the regressor as ``model.width_guard`` refits it:
:func:`facesynth.sadm.fit.refitter`) fitted

* on every training row, its predictions of the **test** frames;
* for each validation slice ``model.width_guard`` scores (:func:`facesynth.model.restore.slice_stops`:
  the last four blocks of the validation's length, ``sadm.val_fraction``), on the rows before
  the slice and a gap as long, its predictions of that **slice** (``slice_K``: the slice ends
  at training row K; the last one is the restoration filter's guard's slice);

each pasted into the real frames and scored over the common region
(:func:`facesynth.eval.frame_level.psnr_common`). ``cost_db``: 128 px's PSNR minus the auto
width's, per segment (positive: the wider frame loses).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

import numpy as np
import torch

from bench.harness import emit
from facesynth.data.shared import shared_data_dir
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.frame_level import psnr_common
from facesynth.landmarks import get_scheme
from facesynth.model.face_model import FaceModel, FaceModelConfig
from facesynth.model.reference import reference_width
from facesynth.model.restore import fit_size, slice_stops
from facesynth.rundir import run_data
from facesynth.runs.config import compose_config, dataclass_from, regressor_params
from facesynth.sadm.fit import SADMConfig, refitter, resolve_sadm_config, validation_size


def clip_costs(clip: str) -> dict:
    cfg = compose_config(["data=video", f"data.path={shared_data_dir() / 'faces' / clip}"])
    seq, tr, te = run_data(cfg)
    common = common_landmarks(seq, None)
    name, params = regressor_params(cfg.regressor)
    sadm_cfg = resolve_sadm_config(name, dataclass_from(cfg.sadm, SADMConfig))
    model_cfg = dataclass_from(cfg.model, FaceModelConfig)
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    auto = reference_width("auto", model_seq.landmarks[tr])
    n_val = validation_size(sadm_cfg, len(tr))

    def score(width, fit_rows, rows):
        model, tex = FaceModel.fit_with_textures(model_seq, replace(model_cfg, reference_width=width), rows=fit_rows,
                                                 progress=False)
        syn = refitter(model, seq, fit_rows, tex, name, params, sadm_cfg)(np.arange(len(fit_rows)))
        with torch.no_grad():
            pred = syn.texture(torch.from_numpy(seq.landmarks[rows])).reshape(len(rows), -1).numpy()
        return psnr_common(model, pred, seq, rows, common[rows], 2.0)

    segments = {"test": (tr, te)}
    for stop in slice_stops(len(tr), n_val):
        segments[f"slice_{stop}"] = (tr[: fit_size(stop, n_val)], tr[stop - n_val : stop])
    out = {"clip": clip, "auto_width": auto, "train": len(tr), "test": len(te), "val_frames": n_val, "segments": {}}
    for seg, (fit_rows, rows) in segments.items():
        base, wide = score(128, fit_rows, rows), score(auto, fit_rows, rows)
        out["segments"][seg] = {"psnr_128": base, "psnr_auto": wide, "cost_db": base - wide}
        print(json.dumps({"clip": clip, "segment": seg, **out["segments"][seg]}), file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clips", default="vrt_face5,lp_d13", help="comma-separated shared clip names")
    args = ap.parse_args()
    if shared_data_dir() is None:
        sys.exit("bench_width_guard: ../shared/data is absent")
    emit({"bench": "width_guard", "clips": [clip_costs(c) for c in args.clips.split(",")]})


if __name__ == "__main__":
    main()
