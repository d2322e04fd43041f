"""Every shared clip x every regressor through the default export and its ONNX Runtime check.

For each clip in ``../shared/data/faces`` (or ``--clips``): the default face model on the
first 75 % of the frames (``--step`` thins the training rows), then every registered
regressor with ``train.py regressor=NAME``'s settings, saved as a run folder and exported by
``facesynth export``'s own function with its defaults (40 components, int8 basis, the
ONNX Runtime vs torch check). Per pair: whether the export passed, the check's largest crop
difference, the recorded int8-vs-float PSNR, the codes' worst int16 pair sum and whether the
file's MatMulInteger is exact on this CPU; or the one-line error.

    OMP_NUM_THREADS=1 python -m bench.export.export_all [--clips lp_d6,lp_d10] [--regressors krr,mlp] [--step 1]

Prints ONE JSON line (``table``: one row per pair; ``passed`` / ``pairs``), with the CPU flags.

``--emulate-cpu EPYC-Rome`` (x86-64 host, Debian's qemu-user) also renders every exported
file in ONNX Runtime under that emulated CPU (AMD EPYC Rome: AVX2, no AVX-512, no VNNI) on
16 held-out frames, and the same model with the 8-bit codes of older files, against torch
(torch itself does not run under the emulator) and against ONNX Runtime on this CPU:
``emulated`` per row, the largest crop differences of each (in 1/255 steps) and whether it
passes the export check, by the int8 parity contract (``facesynth.contract.FLOAT_PARITY_TOL``:
1e-4, plus one code step of each coefficient that the emulated CPU rounds the other way on a tie).
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

from bench.harness import cpu_flags, emit, load_averages

CHILD = """
import json, sys
import numpy as np
from facesynth.onnx.int8check import scaled_coefficients
from facesynth.runtime.renderer import Renderer
from bench.harness import emit
for job in json.load(open(sys.argv[1])):
    lm = np.load(job["landmarks"])
    crop, mask, _ = Renderer(job["onnx"]).render(lm)
    np.savez(job["ort"], crop=crop, mask=mask, x=scaled_coefficients(job["onnx"], {"landmarks": lm}))
"""


def emulation_jobs(run: Path, out: Path, train_lm: np.ndarray, lm: np.ndarray) -> list[dict]:
    """The exported file and an 8-bit-code twin of it (compressed on ``train_lm`` as the
    export did), each with torch's crops on the first 16 rows of ``lm``."""
    from facesynth.contract import LEGACY_CODE_LEVELS
    from facesynth.onnx.synthesis import compress_for_export, export_synthesizer, run_torch
    from facesynth.rundir import load_synthesizer
    from facesynth.runtime import Renderer
    from facesynth.sadm.quantize import quantize_synthesizer

    syn, _ = load_synthesizer(run)
    small, _ = compress_for_export(syn, train_lm)
    jobs = []
    for tag, levels in (("7bit", None), ("8bit", LEGACY_CODE_LEVELS)):
        q = quantize_synthesizer(small, levels=levels)[0] if levels else quantize_synthesizer(small)[0]
        path = out if levels is None else out.with_name(out.stem + "_8bit.onnx")
        if levels is not None:
            export_synthesizer(q, path)
        (crop, mask, _), x_torch = run_torch(q, q.appearance, {"landmarks": lm[:16]})
        stem = path.with_suffix("")
        np.save(f"{stem}_lm.npy", lm[:16])
        native, native_mask, _ = Renderer(path).render(lm[:16])
        np.savez(f"{stem}_torch.npz", crop=crop, mask=mask, native=native, native_mask=native_mask, x=x_torch,
                 codes=q.appearance.basis.codes.numpy(), col_scale=q.appearance.basis.col_scale.numpy())
        jobs.append({"tag": tag, "onnx": str(path), "landmarks": f"{stem}_lm.npy", "torch": f"{stem}_torch.npz",
                     "ort": f"{stem}_ort.npz"})
    return jobs


def run_emulated(jobs: list[dict], cpu: str, work: Path) -> list[dict]:
    """Render every job's file under ``qemu-x86_64 -cpu CPU``; per job the largest crop
    difference inside both masks (1/255 steps) to torch and to ONNX Runtime on this CPU, mask
    flips, and the export check's verdict by the int8 parity contract (as
    ``facesynth.onnx.synthesis.check_export``: 1e-4 plus one code step of each coefficient
    rounded the other way on a tie; a code that differs otherwise fails it)."""
    import subprocess

    from facesynth.contract import FLOAT_PARITY_TOL
    from facesynth.errors import FacesynthError
    from facesynth.onnx.int8check import tie_allowance

    (work / "child.py").write_text(CHILD)
    (work / "jobs.json").write_text(json.dumps(jobs))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    run = subprocess.run(["qemu-x86_64", "-cpu", cpu, sys.executable, str(work / "child.py"), str(work / "jobs.json")],
                         env=env, capture_output=True, text=True)
    if run.returncode:
        raise SystemExit(f"emulated run failed: {run.stderr[-1000:]}")
    out = []
    for job in jobs:
        t, o = np.load(job["torch"]), np.load(job["ort"])
        per_frame = np.abs((o["crop"] - t["crop"]) * o["mask"] * t["mask"]).reshape(len(o["crop"]), -1).max(1)
        native = float(np.abs((o["crop"] - t["native"]) * o["mask"] * t["native_mask"]).max())
        flips = float((o["mask"] != t["mask"]).mean())
        try:
            tol = FLOAT_PARITY_TOL + tie_allowance(t["codes"], t["col_scale"], o["x"], t["x"])
        except FacesynthError:  # a code that differs by more than a tie: fails the check whatever the crops
            tol = np.full(len(per_frame), -1.0)
        out.append({"max_abs_diff_255": round(float(per_frame.max()) * 255, 3), "vs_native_ort_255": round(native * 255, 3),
                    "tolerance_255": round(float(tol.max()) * 255, 3), "tie_flips": int((np.rint(o["x"]) != np.rint(t["x"])).sum()),
                    "mask_flips": flips, "passes_check": bool((per_frame <= tol).all()) and flips <= 1e-3})
    return out


def bench_clip(clip_dir: Path, regressors: list[str], step: int, work: Path, jobs: list | None = None) -> list[dict]:
    import torch

    from facesynth.data import load_sequence, temporal_split
    from facesynth.errors import FacesynthError
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.onnx.export import export_model
    from facesynth.onnx.int8check import matmul_errors, matmul_integer_codes, pair_sum_worst
    from facesynth.progress import set_quiet
    from facesynth.runs.config import train_defaults
    from facesynth.sadm.fit import fit_sadm, save_sadm

    set_quiet(True)
    seq = load_sequence(clip_dir)
    tr, te = temporal_split(len(seq), 0.75, 0)
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
            if jobs is not None:
                row["jobs"] = emulation_jobs(run, out, seq.landmarks[tr], seq.landmarks[te].astype(np.float32))
                jobs += row["jobs"]
        rows.append(row)
    return rows


def main(argv=None) -> int:
    from facesynth.data.shared import shared_data_dir
    from facesynth.regressors import REGISTRY

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clips", default="", help="comma-separated clip names (default: every shared clip)")
    p.add_argument("--regressors", default="", help="comma-separated (default: every registered one)")
    p.add_argument("--step", type=int, default=1, help="training rows: every STEP-th of the first 75 %%")
    p.add_argument("--emulate-cpu", metavar="QEMU_CPU", help="also render each file in ONNX Runtime under qemu-x86_64 -cpu QEMU_CPU")
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
    jobs = [] if args.emulate_cpu else None
    with tempfile.TemporaryDirectory(prefix="bench_export_all_") as d:
        for clip in clips:
            table += bench_clip(clip, regs, args.step, Path(d), jobs)
            print(f"{clip.name}: {sum(r['passed'] for r in table[-len(regs):])}/{len(regs)} passed", file=sys.stderr)
        if jobs:
            results = iter(run_emulated(jobs, args.emulate_cpu, Path(d)))
            for row in table:
                if "jobs" in row:
                    row["emulated"] = {job["tag"]: next(results) for job in row.pop("jobs")}
    out = {"bench": "export_all", "cpu_flags": cpu_flags(), "pairs": len(table), "passed": sum(r["passed"] for r in table),
           "wall_s": round(time.perf_counter() - t0, 1), "loadavg_at_end": load_averages(),
           "worst_pair_sum": max((r.get("pair_sum_worst", 0) for r in table), default=0),
           "min_quantization_psnr_db": min((r["quantization_psnr_vs_float_db"] for r in table if r["passed"]), default=None),
           "max_abs_diff_vs_torch": max((r["max_abs_diff_vs_torch"] for r in table if r["passed"]), default=None),
           "table": table}
    if args.emulate_cpu:
        em = [r["emulated"] for r in table if "emulated" in r]
        out["emulated"] = {"cpu": args.emulate_cpu, "files": len(em),
                           "passed_7bit": sum(e["7bit"]["passes_check"] for e in em),
                           "passed_8bit": sum(e["8bit"]["passes_check"] for e in em),
                           "max_abs_diff_255_7bit": max(e["7bit"]["max_abs_diff_255"] for e in em),
                           "max_abs_diff_255_8bit": max(e["8bit"]["max_abs_diff_255"] for e in em),
                           "vs_native_ort_255_7bit": max(e["7bit"]["vs_native_ort_255"] for e in em),
                           "vs_native_ort_255_8bit": max(e["8bit"]["vs_native_ort_255"] for e in em)}
    emit(out)
    return 0 if out["passed"] == out["pairs"] else 1


if __name__ == "__main__":
    sys.exit(main())
