"""Every shared clip x every regressor through the default export and its ONNX Runtime check.

For each clip in ``../shared/data/faces`` (or ``--clips``): the default face model on the
first 75 % of the frames (``--step`` thins the training rows), then every registered
regressor with ``train.py regressor=NAME``'s settings, saved as a run folder and exported by
``facesynth export``'s own function with its defaults (40 components, int8 basis, the
ONNX Runtime vs torch check). Per pair: whether the export passed, the check's largest crop
difference, the recorded int8-vs-float PSNR, the codes' worst int16 pair sum and whether the
file's MatMulInteger is exact on this CPU; or the one-line error.

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/bench_export_all.py [--clips lp_d6,lp_d10] [--regressors krr,mlp] [--step 1]

Prints ONE JSON line (``table``: one row per pair; ``passed`` / ``pairs``), with the CPU flags.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_int8 import cpu_flags  # noqa: E402


def bench_clip(clip_dir: Path, regressors: list[str], step: int, work: Path) -> list[dict]:
    import torch

    from facesynth.data import load_sequence, temporal_split
    from facesynth.errors import FacesynthError
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.onnx.cli import export_model
    from facesynth.onnx.int8check import matmul_errors, matmul_integer_codes, pair_sum_worst
    from facesynth.progress import set_quiet
    from facesynth.runs.config import train_defaults
    from facesynth.sadm.fit import fit_sadm, save_sadm

    set_quiet(True)
    seq = load_sequence(clip_dir)
    tr, _ = temporal_split(len(seq), 0.75, 0)
    tr = tr[::step]
    t0 = time.perf_counter()
    model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    fit_s = time.perf_counter() - t0
    rows = []
    for reg in regressors:
        row = {"clip": clip_dir.name, "regressor": reg, "train_frames": int(len(tr)), "face_model_s": round(fit_s, 1)}
        t0 = time.perf_counter()
        torch.manual_seed(0)
        name, params, cfg = train_defaults(reg)
        sadm = fit_sadm(model, seq, tr, tex, name, params, cfg, 0)
        run = work / f"{clip_dir.name}_{reg}"
        save_sadm(sadm, run)
        row["fit_s"] = round(time.perf_counter() - t0, 1)
        out = work / f"{clip_dir.name}_{reg}.onnx"
        try:
            summary = export_model(run, out, landmarks=seq.landmarks[tr])
        except FacesynthError as exc:
            row.update({"passed": False, "error": str(exc)})
        else:
            codes = matmul_integer_codes(out)
            row.update({"passed": True, "max_abs_diff_vs_torch": summary["max_abs_diff_vs_torch"],
                        "quantization_psnr_vs_float_db": round(summary["quantization_psnr_vs_float_db"], 2),
                        "bytes": summary["bytes"], "pair_sum_worst": pair_sum_worst(codes),
                        "int8_exact_here": matmul_errors(codes)[0] == 0})
            out.unlink()
        rows.append(row)
    return rows


def main(argv=None) -> int:
    from facesynth.data.shared import shared_data_dir
    from facesynth.regressors import REGISTRY

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", default="", help="comma-separated clip names (default: every shared clip)")
    p.add_argument("--regressors", default="", help="comma-separated (default: every registered one)")
    p.add_argument("--step", type=int, default=1, help="training rows: every STEP-th of the first 75 %%")
    args = p.parse_args(argv)
    data = shared_data_dir()
    faces = None if data is None else data / "faces"
    if faces is None or not faces.is_dir():
        print(json.dumps({"error": "../shared/data/faces is absent"}))
        return 2
    clips = [faces / c for c in args.clips.split(",") if c] or sorted(d for d in faces.iterdir() if d.is_dir())
    regs = [r for r in args.regressors.split(",") if r] or sorted(REGISTRY)
    t0 = time.perf_counter()
    table = []
    with tempfile.TemporaryDirectory(prefix="bench_export_all_") as d:
        for clip in clips:
            table += bench_clip(clip, regs, args.step, Path(d))
            print(f"{clip.name}: {sum(r['passed'] for r in table[-len(regs):])}/{len(regs)} passed", file=sys.stderr)
    out = {"bench": "export_all", "cpu_flags": cpu_flags(), "pairs": len(table), "passed": sum(r["passed"] for r in table),
           "wall_s": round(time.perf_counter() - t0, 1), "loadavg_at_end": [round(v, 2) for v in os.getloadavg()],
           "worst_pair_sum": max((r.get("pair_sum_worst", 0) for r in table), default=0),
           "min_quantization_psnr_db": min((r["quantization_psnr_vs_float_db"] for r in table if r["passed"]), default=None),
           "max_abs_diff_vs_torch": max((r["max_abs_diff_vs_torch"] for r in table if r["passed"]), default=None),
           "table": table}
    print(json.dumps(out, default=lambda v: v.item() if isinstance(v, np.generic) else str(v)))
    return 0 if out["passed"] == out["pairs"] else 1


if __name__ == "__main__":
    sys.exit(main())
