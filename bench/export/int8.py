"""The int8 appearance basis' cost, in one run: float32 vs 8-bit codes (files exported before
the 7-bit codes, which saturate on x86 without VNNI) vs the 7-bit codes exported now.

For each clip: the default face model and SADM (``train.py`` defaults of ``--regressor``,
default krr) fitted on the first 75 % of the frames, compressed as the export does (40
components), then exported three times. Per variant:

* ``texture_psnr_vs_float_db``: the int8 texture against the float one (peak 1), over the
  training and over the held-out landmarks (what the export records, and beyond it);
* ``crop_psnr_vs_float_db``: the ONNX Runtime crops against the float32 file's, held out
  (inside the mask, peak 1), and ``crop_max_abs_vs_float`` (in 1/255 steps);
* ``int8_exact_here``: the file's MatMulInteger against int64 arithmetic on worst-case
  activations on this CPU, and ``pair_sum_worst`` (<= 32767: exact on every CPU);
* ``bytes``, and batch-1 one-thread speed: the three files timed interleaved
  (``bench_onnx_ab.interleaved_times``), median thread-CPU and wall ms, frames/s.

    OMP_NUM_THREADS=1 python -m bench.export.int8 [--clips lp_d6,lp_d10] [--regressor krr]

Prints ONE JSON line, with the CPU's VNNI/AVX2 flags.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.export.onnx_ab import _session, interleaved_times  # noqa: E402
from bench.harness import cpu_flags, emit, load_averages


def bench_clip(clip: str, regressor: str, rounds: int, reps: int) -> dict:
    import torch

    from facesynth.contract import CODE_LEVELS, LEGACY_CODE_LEVELS
    from facesynth.data import load_sequence, shared_clip, temporal_split
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.onnx.int8check import matmul_errors, matmul_integer_codes, pair_sum_worst
    from facesynth.onnx.synthesis import compress_for_export, export_synthesizer
    from facesynth.runs.config import train_defaults
    from facesynth.runtime import Renderer
    from facesynth.sadm.compress import texture_psnr
    from facesynth.sadm.fit import fit_sadm
    from facesynth.sadm.quantize import quantize_synthesizer

    path = shared_clip(clip)
    if path is None:
        return {"error": f"shared clip {clip!r} is absent"}
    seq = load_sequence(path)
    tr, te = temporal_split(len(seq), 0.75, 0)
    torch.manual_seed(0)
    model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    name, params, sadm_cfg = train_defaults(regressor)
    syn = fit_sadm(model, seq, tr, tex, name, params, sadm_cfg).synthesizer()
    lm_tr, lm_te = seq.landmarks[tr].astype(np.float32), seq.landmarks[te].astype(np.float32)
    small, _ = compress_for_export(syn, lm_tr)
    variants = {"float32": small}
    for tag, levels in (("int8_8bit", LEGACY_CODE_LEVELS), ("int8_7bit", CODE_LEVELS)):
        variants[tag] = quantize_synthesizer(small, levels=levels)[0]
    out = {"clip": clip, "regressor": regressor, "train_frames": int(len(tr)), "heldout_frames": int(len(te)),
           "reference_size": list(model.reference.size), "appearance_components": int(small.appearance.components.shape[0]),
           "variants": {}}
    with tempfile.TemporaryDirectory(prefix="bench_int8_") as d:
        files = {tag: export_synthesizer(s, Path(d) / f"{tag}.onnx") for tag, s in variants.items()}
        crops = {tag: Renderer(p).render(lm_te) for tag, p in files.items()}
        ref_crop, ref_mask = crops["float32"][0], crops["float32"][1]
        for tag, s in variants.items():
            crop, mask, _ = crops[tag]
            inside = (mask * ref_mask) > 0
            inside = np.broadcast_to(inside, crop.shape)
            diff = (crop - ref_crop)[inside]
            mse = float(np.mean(diff.astype(np.float64) ** 2))
            entry = {"bytes": files[tag].stat().st_size,
                     "crop_psnr_vs_float_db": None if mse == 0 else round(10 * np.log10(1.0 / mse), 2),
                     "crop_max_abs_vs_float_255": round(float(np.abs(diff).max()) * 255, 3)}
            if tag != "float32":
                entry["texture_psnr_vs_float_db"] = {"train": round(texture_psnr(small, s, lm_tr), 2),
                                                     "heldout": round(texture_psnr(small, s, lm_te), 2)}
                codes = matmul_integer_codes(files[tag])
                wrong, worst = matmul_errors(codes)
                entry.update({"code_levels": int(np.abs(codes.astype(np.int64)).max()),
                              "pair_sum_worst": pair_sum_worst(codes), "int8_exact_here": wrong == 0,
                              "int8_wrong_outputs_here": wrong, "int8_max_error_here": worst})
            out["variants"][tag] = entry
        sessions = [_session(str(p)) for p in files.values()]
        wall, cpu = interleaved_times(sessions, lm_te, rounds, reps)
    for tag, w, c in zip(variants, wall, cpu, strict=True):
        w, c = np.asarray(w) * 1e3, np.asarray(c) * 1e3
        out["variants"][tag].update({"cpu_ms_p50": round(float(np.median(c)), 4), "wall_ms_p50": round(float(np.median(w)), 4),
                                     "frames_per_s_cpu": round(1e3 / float(np.median(c)), 1),
                                     "wall_ms_best_round_p50": round(float(np.median(w, 1).min()), 4)})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", default="lp_d6")
    p.add_argument("--regressor", default="krr")
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--reps", type=int, default=200)
    args = p.parse_args(argv)
    out = {"bench": "int8", "cpu_flags": cpu_flags(), "loadavg_at_start": load_averages(),
           "clips": [bench_clip(c, args.regressor, args.rounds, args.reps) for c in args.clips.split(",") if c]}
    out["loadavg_at_end"] = load_averages()
    emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
