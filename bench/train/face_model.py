"""Face model benchmark: fitting time and peak memory on a real clip (all frames), and
batched piecewise-affine warp throughput at the 128-px reference.

    python -m bench.train.face_model [--clip lp_d6] [--synthetic] [--threads 1]

Prints one JSON line.
"""

import argparse
import resource
import sys
import time

import numpy as np
import torch

from bench.harness import emit


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clip", default="lp_d6")
    ap.add_argument("--synthetic", action="store_true", help="use the synthetic subject (no shared data needed)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batch", type=int, default=32)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from facesynth.data import load_sequence, shared_clip
    from facesynth.model import FaceModel, FaceModelConfig

    if args.synthetic or shared_clip(args.clip) is None:
        from facesynth.data.synthetic import make_synthetic_sequence

        seq, name = make_synthetic_sequence(300, 256, seed=0), "synthetic"
    else:
        seq, name = load_sequence(shared_clip(args.clip)), args.clip
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    model = FaceModel.fit(seq, FaceModelConfig(reference_width=128), progress=False)
    fit_s = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    # warp throughput: image -> reference (sampling) and reference -> target (rendering)
    frames = seq.load_frames(np.arange(min(args.batch, len(seq))))
    lm = torch.from_numpy(seq.landmarks[: len(frames)])
    x = torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 255
    sampler, target_warp = model.sampler(), model.target_warp()
    canvas = torch.from_numpy(model.to_canvas(seq.landmarks[: len(frames)])[0])

    def rate(fn, n):
        with torch.no_grad():
            fn()
            best = []
            for _ in range(5):
                t = time.perf_counter()
                fn()
                best.append(time.perf_counter() - t)
        return n / float(np.median(best))

    with torch.no_grad():
        tex = sampler(x, lm)
    out = {
        "bench": "face_model",
        "data": name,
        "frames": len(seq),
        "image_size": list(seq.image_size),
        "fit_seconds": round(fit_s, 3),
        "fit_breakdown_s": {k: round(v, 3) for k, v in model.meta["fit_seconds"].items()},
        "peak_rss_mb": round(peak_mb, 1),
        "rss_before_fit_mb": round(rss0 / 1024, 1),
        "n_shape": model.shape_pca.n_components,
        "n_appearance": model.appearance_pca.n_components,
        "reference_size": list(model.reference.size),
        "threads": args.threads,
        "batch": len(frames),
        "warp_to_reference_fps": round(rate(lambda: sampler(x, lm), len(frames)), 1),
        "warp_to_target_fps": round(rate(lambda: target_warp(tex, canvas), len(frames)), 1),
        "warp_to_target_fps_batch1": round(rate(lambda: target_warp(tex[:1], canvas[:1]), 1), 1),
        "torch": torch.__version__,
        "python": sys.version.split()[0],
    }
    emit(out)
if __name__ == "__main__":
    main()
