"""Where the sigma 0 -> 2 loss of frame-level PSNR comes from, and what a denoised warp
target would win (issue 14's noise bound). This measurement led to the face model's
landmark denoising (``model.denoise_variance``, docs/sadm.md), which ``FaceModel.render``
applies itself: give it runs trained with ``model.denoise_variance=1`` (or before it
existed) for ``raw`` to mean the landmarks as given.

    python -m bench.studies.target_denoise RUN [RUN ...] [--frames 40] [--sigma 2]

For each training run (``train.py``; any scheme) and about ``--frames`` evenly spaced test
frames, the SADM's predicted texture (from clean, and from noisy landmarks: seeded Gaussian
noise of ``--sigma`` frame px, as the evaluation adds it) is warped onto

* ``raw``: the landmarks as given (what the synthesis graph does today);
* ``pca_model``: the landmarks projected on the face model's own shape PCA (similarity-
  aligned, reconstructed, mapped back to the frame);
* ``pca_999``: projected on a PCA of the run's training shapes keeping 99.9 % of their
  variance (K components, printed);

and composited into the real frame; PSNR (dB) over the common region (convex hull of the
frame's dlib points 0-26 eroded 3 px: ``facesynth.eval.common_region``). ``rewarp``: the
frame's own texture instead of the prediction (the geometry alone). One JSON line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.harness import emit  # noqa: E402
from facesynth.compositing import composite  # noqa: E402
from facesynth.eval.common_region import common_landmarks, hull_box, region_masks  # noqa: E402
from facesynth.eval.sadm_eval import noisy_landmarks  # noqa: E402
from facesynth.geometry import apply_affine, invert_affine  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.sadm.fit import load_sadm  # noqa: E402


def measure(run, n_frames: int, sigma: float) -> dict:
    """The figures of one run (module docstring)."""
    seq, tr, te = run_data(read_config(run))
    sadm = load_sadm(run)
    model = sadm.model
    n_model = model.mean_shape.shape[0]
    rows = te[:: max(1, len(te) // n_frames)]
    common = common_landmarks(seq)[rows]
    full = np.asarray(seq.landmarks[rows], np.float32)
    noisy = np.concatenate([noisy_landmarks(full[j : j + 1], sigma, 17 * int(r), n_model)
                            for j, r in enumerate(rows)]).astype(np.float32)
    frames = [seq.frame(int(r)) for r in rows]
    own = model.sample_textures(seq, rows)

    aligned_tr, _ = model.align(np.asarray(seq.landmarks[tr][:, :n_model], np.float32))
    x = aligned_tr.reshape(len(tr), -1)
    mu = x.mean(0)
    _, s, vt = np.linalg.svd(x - mu, full_matrices=False)
    k999 = int(np.searchsorted(np.cumsum(s**2) / np.sum(s**2), 0.999) + 1)
    basis = vt[:k999]

    def target(lm: np.ndarray, kind: str) -> np.ndarray:
        pts = lm[:, :n_model]
        if kind == "raw":
            return pts
        al, t = model.align(pts)
        if kind == "pca_model":
            rec = model.shape_from_params(model.shape_params(pts))
        else:
            rec = ((al.reshape(len(al), -1) - mu) @ basis.T @ basis + mu).reshape(al.shape)
        return apply_affine(rec, invert_affine(t)).astype(np.float32)  # back to the frame

    def psnr(tex: np.ndarray, targets: np.ndarray) -> float:
        crop, mask, place = model.render(tex, targets)
        se, n = 0.0, 0
        for j, fr in enumerate(frames):
            img = composite(crop[j], mask[j], place[j], fr)
            y0, y1, x0, x1 = box = hull_box(common[j], fr.shape[:2], 0)
            m = region_masks(common[j], box)["whole"]
            d = img[y0:y1, x0:x1].astype(np.float64)[m] - fr[y0:y1, x0:x1].astype(np.float64)[m]
            se, n = se + float((d**2).sum()), n + d.size
        return round(10 * np.log10(255.0**2 / (se / n)), 2)

    res = {"scheme": sadm.scheme, "frames": len(rows), "shape_components_model": int(model.shape_pca.n_components),
           "shape_components_999": k999}
    pred = {name: np.clip(model.texture_from_params(sadm.predict_params(lm)), 0, 1) for name, lm in
            (("clean", full), ("noisy", noisy))}
    for kind in ("raw", "pca_model", "pca_999"):
        res[kind] = {"sadm_clean": psnr(pred["clean"], target(full, kind)),
                     "sadm_noisy": psnr(pred["noisy"], target(noisy, kind)),
                     "rewarp_clean": psnr(own, target(full, kind)),
                     "rewarp_noisy": psnr(own, target(noisy, kind))}
        res[kind]["sadm_loss"] = round(res[kind]["sadm_clean"] - res[kind]["sadm_noisy"], 2)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--sigma", type=float, default=2.0)
    args = ap.parse_args()
    out = {"sigma": args.sigma, "runs": {}}
    for run in args.runs:
        out["runs"][str(run)] = measure(run, args.frames, args.sigma)
    emit(out)
if __name__ == "__main__":
    main()
