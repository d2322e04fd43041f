"""How far can landmarks alone predict held-out appearance? A distribution-shift study.

The held-out figure (train on the first 75 %, test on the last 25 %) mixes two losses:
(1) what the landmarks cannot explain at all (gaze, tongue/teeth, illumination drift) and
(2) the shift between the training and test segments (expressions never shown before).
This study separates them. The test segment is cut into halves A and B (in time); the
same SADM settings are fitted on

* ``train``          (the standard held-out setting) and scored on B,
* ``train + A``      (the test distribution partly covered) and scored on B,

in the reference frame over the mask, PSNR peak 255, sigma 0 (no landmark noise). The
face model (shape/appearance PCA) is the one fitted on the training segment in both
rows, so the difference is the regressor's data only. If even ``train + A`` stays below
a target, the target is out of reach for a landmark-driven predictor on that face model,
whatever the regressor (the appearance PCA oracle is printed as the representational
bound).

Run::

    PYTHONPATH=. python -m facesynth.sadm.ceiling --clip /work/shared/data/faces/lp_d6 \
        [--regressor krr] [--json OUT]

prints one JSON line: clip, regressor, frames, and PSNR (dB) of the mean texture, the
PCA oracle, ``train -> B`` and ``train+A -> B``.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def psnr_ref(model, b: np.ndarray, tex: np.ndarray) -> float:
    """PSNR (peak 255) of the textures of parameters ``b`` (N, K_g) vs ``tex`` (N, C*M)."""
    from facesynth.eval.metrics import psnr

    return psnr(np.clip(model.texture_from_params(b), 0, 1) * 255.0, np.clip(tex, 0, 1) * 255.0)


def study(clip: str, regressor: str = "krr", params: dict | None = None, train_fraction: float = 0.75) -> dict:
    """The figures of the module docstring for one clip (a folder readable by load_sequence)."""
    from facesynth.data import load_sequence, temporal_split
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.sadm.fit import SADMConfig, fit_sadm

    seq = load_sequence(clip)
    tr, te = temporal_split(len(seq), train_fraction)
    model, tex_tr = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=tr, progress=False)
    tex_te = model.sample_textures(seq, te)
    half = len(te) // 2
    rows_a, rows_b = te[:half], te[half:]
    tex_a, tex_b = tex_te[:half], tex_te[half:]
    lm_b = seq.landmarks[rows_b]
    out = {
        "clip": str(clip), "regressor": regressor, "train_frames": int(len(tr)), "test_b_frames": int(len(rows_b)),
        "mean_texture": psnr_ref(model, np.zeros((len(rows_b), model.appearance_pca.n_components)), tex_b),
        "oracle": psnr_ref(model, model.appearance_params(tex_b), tex_b),
    }
    for key, rows, tex in (("train_to_B", tr, tex_tr), ("train_plus_A_to_B", np.r_[tr, rows_a], np.concatenate([tex_tr, tex_a]))):
        sadm = fit_sadm(model, seq, rows, tex, regressor, params, SADMConfig())
        out[key] = psnr_ref(model, sadm.predict_params(lm_b), tex_b)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clip", required=True, help="clip folder (video + landmarks)")
    ap.add_argument("--regressor", default="krr")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)
    res = study(args.clip, args.regressor)
    line = json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in res.items()})
    print(line)
    if args.json:
        from facesynth.io import write_text

        write_text(args.json, line + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
