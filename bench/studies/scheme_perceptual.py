"""ibug68 against mediapipe478 per clip, by PSNR and by LPIPS: one JSON line per clip.

    OMP_NUM_THREADS=1 python -m bench.studies.scheme_perceptual --dense RUN_MP/lp_d3 RUN_MP/vrt_face2 \\
        --base RUN_IB/lp_d3 RUN_IB/vrt_face2 [--outline 2]

Each pair: two ``train.py`` runs of one clip in the default configuration (the dense one on a
``facesynth ingest --landmarker mediapipe`` folder of the same video), with the frame-level
evaluation. From their ``metrics.json`` (held out, sigma 0, row ``sadm`` unless named):
``psnr_frame_common`` whole and rest (dB), ``lpips_frame_common`` face, eyes and mouth (the
face pasted into the real frame with each model's own mask, feathered, no colour match,
scored on the common region's box plus 10 %; lower is closer), the ``rewarp`` row's whole PSNR
and face LPIPS (the frame's own texture through each reference frame: what the render path
allows) and ``sharpness_frame_common`` whole.

``--outline N``: every Nth held-out frame rendered again by both models (:func:`outline_check`):
the face LPIPS of each pasted with its own mask, and of the dense model's face pasted with
its alpha cut to the ibug68 model's (the same outline, feather 3 px; ``lpips_dense_cut``): how
much of the dense scheme's loss is the wider area it renders (forehead, temples) inside the
scored box, where the ibug68 paste shows the real frame itself.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

FEATHER = 3.0  # px, the paste's soft edge in outline_check (the frame-level evaluation's default)


def figures(metrics: dict) -> dict:
    reg, lp = metrics["psnr_frame_common_regions"], metrics.get("lpips_frame_common", {})
    out = {"psnr_whole_db": reg["whole"]["sadm"]["0"], "psnr_rest_db": reg["rest"]["sadm"]["0"],
           "psnr_rewarp_db": reg["whole"]["rewarp"]["0"], "sharpness": metrics["sharpness_frame_common"]["whole"]["sadm"]}
    for part in ("face", "eyes", "mouth"):
        if part in lp:
            out[f"lpips_{part}"] = lp[part]["sadm"]
    if "face" in lp:
        out["lpips_rewarp_face"] = lp["face"]["rewarp"]
    return {k: round(float(v), 4) for k, v in out.items()}


def outline_check(base_run: str, dense_run: str, step: int) -> dict:
    """Median face LPIPS over every ``step``-th held-out frame: ibug68 and the dense model
    pasted with their own masks, and the dense one with its alpha cut to ibug68's."""
    import cv2
    import torch

    from facesynth.eval import perceptual
    from facesynth.eval.reenact import hull_mask
    from facesynth.rundir import read_config, run_data
    from facesynth.sadm.fit import load_sadm

    data = [run_data(read_config(r)) for r in (base_run, dense_run)]
    syns = [load_sadm(r).synthesizer() for r in (base_run, dense_run)]
    seq, _, te = data[0]
    r = int(np.ceil(FEATHER))
    scores: dict[str, list[float]] = {"lpips_base": [], "lpips_dense": [], "lpips_dense_cut": []}
    for row in te[::step]:
        row = int(row)
        frame = np.asarray(seq.frame(row))
        size = frame.shape[1::-1]
        box = perceptual.region_box(hull_mask(np.asarray(seq.landmarks[row][:27], np.float64), frame.shape[:2], 3))
        faces, alphas = [], []
        for (s, _, _), syn in zip(data, syns, strict=True):
            with torch.no_grad():
                c, m, pl = (t.numpy() for t in syn(torch.from_numpy(np.asarray(s.landmarks[row:row + 1], np.float32))))
            place = pl[0].astype(np.float64)
            faces.append(np.clip(cv2.warpAffine(np.ascontiguousarray(c[0].transpose(1, 2, 0)), place, size), 0, 1))
            hard = (cv2.warpAffine(m[0, 0], place, size) > 0.999).astype(np.float32)
            alphas.append(cv2.GaussianBlur(cv2.erode(hard, np.ones((2 * r + 1, 2 * r + 1), np.uint8)), (0, 0), FEATHER / 2) * hard)
        bg = frame.astype(np.float32) / 255.0

        def paste(face, a, bg=bg):
            return np.clip((a[..., None] * face + (1 - a[..., None]) * bg) * 255.0 + 0.5, 0, 255).astype(np.uint8)

        real = perceptual.region_crop(frame, box)
        shown = {"lpips_base": paste(faces[0], alphas[0]), "lpips_dense": paste(faces[1], alphas[1]),
                 "lpips_dense_cut": paste(faces[1], np.minimum(alphas[0], alphas[1]))}
        for k, img in shown.items():
            scores[k].append(float(perceptual.lpips(real, perceptual.region_crop(img, box))[0]))
    return {"outline_frames": len(scores["lpips_base"]), **{k: round(float(np.median(v)), 4) for k, v in scores.items()}}


def main() -> None:
    from bench.harness import add_scheme_pairs, scheme_pairs

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_scheme_pairs(p, "mediapipe478")
    p.add_argument("--outline", type=int, default=0, help="also render every Nth held-out frame (0: off)")
    a = p.parse_args()
    for d, b, md, mb in scheme_pairs(a):
        line = {"bench": "scheme_perceptual", "clip": md.get("data", {}).get("name", Path(d).name),
                "schemes": [mb.get("landmark_scheme"), md.get("landmark_scheme")],
                "ibug68": figures(mb), "mediapipe478": figures(md)}
        if a.outline:
            line.update(outline_check(b, d, a.outline))
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
