"""SADM benchmark: training time per regressor on a real clip (all defaults, temporal
75/25 split) and per-frame synthesis time of the torch graph (batch 1 and batch 32).

    python -m bench.train.sadm [--clip lp_d6] [--only linear,svr] [--threads 1]

Prints one JSON line.
"""

import argparse
import time

import numpy as np
import torch

from bench.harness import emit


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clip", default="lp_d6")
    ap.add_argument("--only", default="linear,poly2,mlp,svr,krr")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from facesynth.data import load_sequence, shared_clip, temporal_split
    from facesynth.metrics import psnr
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.runs.config import train_defaults
    from facesynth.sadm.fit import fit_sadm

    if shared_clip(args.clip) is None:
        from facesynth.data.synthetic import make_synthetic_sequence

        seq, name = make_synthetic_sequence(240, 256, seed=0), "synthetic"
    else:
        seq, name = load_sequence(shared_clip(args.clip)), args.clip
    tr, te = temporal_split(len(seq), 0.75)
    t0 = time.perf_counter()
    model, tex_tr = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    model_s = time.perf_counter() - t0
    tex_te = model.sample_textures(seq, te)
    result = {"bench": "sadm", "data": name, "train_frames": len(tr), "test_frames": len(te),
              "face_model_fit_s": round(model_s, 2), "threads": args.threads, "regressors": {}}
    for reg in args.only.split(","):
        rname, params, sadm_cfg = train_defaults(reg)
        t = time.perf_counter()
        sadm = fit_sadm(model, seq, tr, tex_tr, rname, params, sadm_cfg, seed=0)
        fit_s = time.perf_counter() - t
        syn = sadm.synthesizer()
        lm1 = torch.from_numpy(seq.landmarks[te[:1]])
        lm32 = torch.from_numpy(seq.landmarks[te[:32]])
        times = {}
        with torch.no_grad():
            for key, x in (("batch1", lm1), ("batch32", lm32)):
                syn(x)
                reps = []
                for _ in range(7):
                    s = time.perf_counter()
                    syn(x)
                    reps.append((time.perf_counter() - s) / len(x))
                times[key] = float(np.median(reps)) * 1000
            pred = torch.cat([syn.texture(torch.from_numpy(seq.landmarks[te[i:i + 64]])).reshape(len(te[i:i + 64]), -1)
                              for i in range(0, len(te), 64)]).numpy()
        result["regressors"][reg] = {
            "train_s": round(fit_s, 2),
            "synth_ms_per_frame_batch1": round(times["batch1"], 3),
            "synth_ms_per_frame_batch32": round(times["batch32"], 3),
            "psnr_ref_test_sigma0": round(psnr(pred * 255, tex_te * 255), 2),
            **{k: v for k, v in sadm.regressor.summary().items() if isinstance(v, (int, float))},
        }
    result["mean_texture_psnr_ref"] = round(psnr(np.clip(model.appearance_pca.mean, 0, 1)[None].repeat(len(te), 0) * 255, tex_te * 255), 2)
    emit(result)
if __name__ == "__main__":
    main()
