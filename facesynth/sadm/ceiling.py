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

Where the error lies: :func:`facesynth.sadm.regions.reference_regions` cuts the reference
frame into the face's parts (the one definition, :func:`facesynth.landmarks.face_region_masks`:
eyes, mouth interior, lips, the brow-to-upper-eyelid bands, the rest), and
:func:`region_breakdown` reports each region's share of the pixels and of the squared
error, its PSNR and the oracle's. ``regions`` in the output holds that breakdown for
both rows, plus ``*_eyes_interior_at_oracle``: the PSNR if the eyes and the mouth
interior alone were predicted as well as the appearance PCA can represent them. If the
eyes and the mouth interior stay far below the oracle even in ``train + A``, the missing
information is gaze and tongue/teeth state, which the 68 landmarks do not carry.

Run::

    python -m facesynth.sadm.ceiling --clip ../shared/data/faces/CLIP \
        [--regressor krr] [--augment-sigma 1] [--json OUT]

prints one JSON line: clip, regressor, frames, and PSNR (dB) of the mean texture, the
PCA oracle, ``train -> B`` and ``train+A -> B``, and the region breakdown.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from facesynth.data import load_sequence, temporal_split
from facesynth.io import write_text
from facesynth.metrics import psnr
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.sadm.fit import SADMConfig, fit_sadm
from facesynth.sadm.regions import reference_regions


def psnr_ref(model, b: np.ndarray, tex: np.ndarray) -> float:
    """PSNR (peak 255) of the textures of parameters ``b`` (N, K_g) vs ``tex`` (N, C*M)."""
    return psnr(np.clip(model.texture_from_params(b), 0, 1) * 255.0, np.clip(tex, 0, 1) * 255.0)


def region_breakdown(model, pred: np.ndarray, true: np.ndarray, oracle: np.ndarray) -> dict:
    """Per region of :func:`~facesynth.sadm.regions.reference_regions`: share of the pixels, share of the squared error
    of ``pred``, PSNR of ``pred`` and of ``oracle`` (all (N, C*M) textures in [0, 1]), and
    ``eyes_interior_at_oracle``: the overall PSNR with the eyes and mouth interior taken
    from ``oracle``."""
    c = model.n_channels
    n = len(true)
    err = ((np.clip(pred, 0, 1) - true) * 255.0).reshape(n, c, -1) ** 2
    err_o = ((np.clip(oracle, 0, 1) - true) * 255.0).reshape(n, c, -1) ** 2
    total = err.sum()
    out: dict = {}
    r = reference_regions(model)
    for name, m in r.items():
        out[name] = {"pixel_share": float(m.mean()), "error_share": float(err[:, :, m].sum() / total),
                     "psnr": float(10 * np.log10(255.0**2 / err[:, :, m].mean())),
                     "oracle_psnr": float(10 * np.log10(255.0**2 / err_o[:, :, m].mean()))}
    swap = r["eyes"] | r["mouth_interior"]
    mixed = (total - err[:, :, swap].sum() + err_o[:, :, swap].sum()) / err.size
    out["eyes_interior_at_oracle"] = float(10 * np.log10(255.0**2 / mixed))
    return out


def study(clip: str, regressor: str = "krr", params: dict | None = None, train_fraction: float = 0.75,
          sadm_params: dict | None = None) -> dict:
    """The figures of the module docstring for one clip (a folder readable by load_sequence).

    ``params``: regressor hyper-parameters (default: the regressor's config defaults);
    ``sadm_params``: :class:`~facesynth.sadm.fit.SADMConfig` fields (default: those
    ``fit_sadm`` uses for the regressor, e.g. 1 px augmentation for krr)."""
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
    oracle_b = model.texture_from_params(model.appearance_params(tex_b))
    regions = {}
    for key, rows, tex in (("train_to_B", tr, tex_tr), ("train_plus_A_to_B", np.r_[tr, rows_a], np.concatenate([tex_tr, tex_a]))):
        # the regressor's own b_g is scored (texture_from_params), so the per-part shrinkage is not fitted
        sadm = fit_sadm(model, seq, rows, tex, regressor, params, SADMConfig(**{"region_shrink": False, **(sadm_params or {})}))
        b = sadm.predict_params(lm_b)
        out[key] = psnr_ref(model, b, tex_b)
        regions[key] = region_breakdown(model, model.texture_from_params(b), tex_b, oracle_b)
    out["regions"] = regions
    return out


def _rounded(v):
    if isinstance(v, dict):
        return {k: _rounded(x) for k, x in v.items()}
    return round(v, 3) if isinstance(v, float) else v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clip", required=True, help="clip folder (video + landmarks)")
    ap.add_argument("--regressor", default="krr")
    ap.add_argument("--augment-sigma", type=float, default=None,
                    help="landmark-noise augmentation in px (default: the regressor's own, krr 1 px, as train.py)")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)
    res = study(args.clip, args.regressor, sadm_params={"augment_sigma": args.augment_sigma})
    line = json.dumps(_rounded(res))
    print(line)
    if args.json:
        write_text(args.json, line + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
