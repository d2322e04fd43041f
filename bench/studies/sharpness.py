"""Where a run's rendered detail goes, stage by stage; prints one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.sharpness RUN_DIR [--onnx MODEL.onnx] [--frames 40]

Sharpness S (facesynth.eval.sharpness: Sobel gradient energy of the face pasted into the real
frame with blend_face over the real frame's, median over frames) over the common region
(dlib hull 0-26 eroded 3 px, facesynth.eval.common_region) of held-out frames, sigma 0, for:

* ``rewarp``: the frame's own texture sampled into the reference frame and rendered back
  (what the reference frame's resolution and the warp keep);
* ``oracle``: that texture projected on the appearance PCA (what the basis keeps);
* ``sadm``: the run's prediction from the landmarks, in torch (what the regressor keeps);
* ``exported``: the same through the exported ONNX model (``--onnx``; default: exported here
  with ``facesynth export``'s defaults into a temporary folder), rendered with ONNX Runtime.

Also the frame-level PSNR over the common region of each stage (dB; as ``psnr_frame_common``:
feathered paste without colour matching; the exported stage's
``psnr_frame_common_blend_face`` is pasted with blend_face, colour matched at the seam as the
app shows it, so it reads higher than the others). RUN_DIR is a train.py
run; its config names the data and the split. The clip needs its dlib landmarks (as
``psnr_frame_common``).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from bench.harness import emit
from facesynth import progress  # noqa: E402
from facesynth.compositing import blend_rendered  # noqa: E402
from facesynth.eval.common_region import common_landmarks, hull_box, region_masks  # noqa: E402
from facesynth.eval.frame_level import subset  # noqa: E402
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm  # noqa: E402
from facesynth.eval.sharpness import sharpness  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.runtime.renderer import Renderer  # noqa: E402
from facesynth.sadm.fit import load_sadm  # noqa: E402


def exported_stage(model_path: Path, seq, rows: np.ndarray, common: np.ndarray) -> tuple[float, float]:
    """(median S, pooled PSNR dB) over the whole common region of the ONNX model's renders of ``rows``."""
    rend = Renderer(model_path, threads=1)
    scores, sq, count = [], 0.0, 0
    for j, frame in enumerate(seq.iter_frames(rows)):
        crops, masks, places = rend.render(seq.landmarks[rows[j : j + 1]], copy=True)
        shown = blend_rendered(crops, masks, places, frame)
        box = hull_box(common[j], frame.shape[:2], 8)
        y0, y1, x0, x1 = box
        m = region_masks(common[j], box)["whole"]
        scores.append(sharpness(shown[y0:y1, x0:x1], frame[y0:y1, x0:x1], {"whole": m})["whole"])
        d = shown[y0:y1, x0:x1].astype(np.float64) - frame[y0:y1, x0:x1]
        sq += float((d[m] ** 2).sum())
        count += 3 * int(m.sum())
    return float(np.nanmedian(scores)), float(10 * np.log10(255.0**2 / (sq / count)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--onnx", type=Path, default=None, help="exported model (default: export the run here)")
    ap.add_argument("--frames", type=int, default=40, help="evenly spaced held-out frames (default 40)")
    args = ap.parse_args()
    progress.set_quiet(True)
    cfg = read_config(args.run)
    seq, tr, te = run_data(cfg)
    sadm = load_sadm(args.run)
    common = common_landmarks(seq)
    ecfg = EvalConfig(noise=[0.0], max_test_frames=args.frames, train_level=False)
    m, _ = evaluate_sadm(sadm, seq, tr, te, ecfg, int(cfg.seed), common=common)
    stages = {k: {"sharpness": m["sharpness_frame_common"]["whole"][k], "psnr_frame_common": m["psnr_frame_common"][k]["0"]}
              for k in ("rewarp", "oracle", "sadm", "mean_texture")}
    rows = te[subset(len(te), args.frames)]
    with tempfile.TemporaryDirectory() as tmp:
        path = args.onnx
        if path is None:
            from facesynth.onnx.export import export_model

            path = Path(tmp) / "model.onnx"
            export_model(args.run, path)
        s, p = exported_stage(path, seq, rows, common[rows])
    stages["exported"] = {"sharpness": s, "psnr_frame_common_blend_face": p}
    out = {"run": str(args.run), "data": seq.name, "frames": int(len(rows)), "reference_size": list(sadm.model.reference.size),
           "face_width_px": float(np.median(np.ptp(common[rows][:, :17, 0], axis=1))),
           "stages": {k: {a: round(b, 3) for a, b in v.items()} for k, v in stages.items()}}
    emit(out)
if __name__ == "__main__":
    main()
