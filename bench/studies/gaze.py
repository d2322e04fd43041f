"""The gaze study of docs/sadm.md ("Gaze"): on ``ibug68+iris`` folders (dlib's 68 points +
MediaPipe's irises), held-out reference-frame PSNR of the default SADM (krr) without gaze
(``main``: the ibug68 model), with the gaze path (``gaze``: cross-fitted residuals;
``gaze_in_sample``), with the gaze features inside the main regressor (``inside``: once,
``inside_x4``: 4 copies, i.e. twice the weight after z-scoring) and with both (``both``);
whole face and the eye region (docs/sadm.md's region masks).

Protocol as ``train.py`` (default config): temporal split 75/25, one face model on the
training segment's 68 dlib points, krr with its 1 px / 4-copy augmentation (the same noise
draws on points 0-67 in every variant), landmark noise as :mod:`facesynth.eval.sadm_eval`
(sigma 2 on all 78 points). ``main only`` is the ``ibug68`` model: its 68-point noise draws
and fit are those of ``train.py`` on the shipped dlib folder.

    python -m bench.studies.gaze --dirs /tmp/gaze/lp_d6 [/tmp/gaze/lp_d10 ...] [--only main,gaze]

where each DIR is an ``ibug68+iris`` folder (``facesynth ingest VIDEO --landmarker dlib+iris``
or :func:`facesynth.data.iris.add_irises`). Prints ONE JSON line:
``{clip: {variant: {"psnr_ref": [sigma 0, sigma 2], "eyes": [sigma 0, sigma 2], "alpha": ...}}}``.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np
import torch

from facesynth.data import load_sequence, temporal_split
from facesynth.eval.sadm_eval import noisy_landmarks
from facesynth.metrics import psnr
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.sadm.fit import SADMConfig, fit_sadm, resolve_sadm_config
from facesynth.sadm.regions import reference_regions as region_masks

VARIANTS = ("main", "gaze", "gaze_in_sample", "gaze_eyes", "gaze_eyes_in_sample", "inside", "inside_x4", "both",
            "both_eyes")


def study(path: str, only=VARIANTS, seed: int = 0) -> dict:
    seq = load_sequence(path)
    if seq.scheme != "ibug68+iris":
        raise SystemExit(f"{path}: expected an ibug68+iris folder, got {seq.scheme}")
    tr, te = temporal_split(len(seq), 0.75, 0)
    model, tex_tr = FaceModel.fit_with_textures(seq.to_scheme("ibug68"), FaceModelConfig(), rows=tr, progress=False)
    tex_te = model.sample_textures(seq.to_scheme("ibug68"), te)
    eyes = region_masks(model)["eyes"]
    c = model.n_channels
    lm_te = {s: noisy_landmarks(seq.landmarks[te], s, seed, base_points=68) for s in (0.0, 2.0)}

    def score(syn):
        out = {"psnr_ref": [], "eyes": []}
        for s in (0.0, 2.0):
            with torch.no_grad():
                pred = np.concatenate([syn.texture(torch.from_numpy(lm_te[s][i:i + 64])).reshape(-1, tex_te.shape[1]).numpy()
                                       for i in range(0, len(te), 64)]) * 255.0
            true = np.clip(tex_te, 0, 1) * 255.0
            out["psnr_ref"].append(round(psnr(pred, true), 3))
            e = (pred - true).reshape(len(te), c, -1)[:, :, eyes]
            out["eyes"].append(round(float(10 * np.log10(255.0**2 / (e**2).mean())), 3))
        return out

    base = resolve_sadm_config("krr", SADMConfig(region_shrink=False))  # the gaze study predates the per-part shrinkage
    configs = {"main": replace(base, gaze=False), "gaze": replace(base, gaze_mode="path", gaze_target="params"),
               "gaze_in_sample": replace(base, gaze_mode="path", gaze_target="params", gaze_folds=0),
               "gaze_eyes": replace(base, gaze_mode="path", gaze_target="eyes"),
               "gaze_eyes_in_sample": replace(base, gaze_mode="path", gaze_target="eyes", gaze_folds=0),
               "both_eyes": replace(base, gaze_mode="both", gaze_copies=4, gaze_target="eyes"),
               "inside": replace(base, gaze_mode="inside", gaze_copies=1),
               "inside_x4": replace(base, gaze_mode="inside", gaze_copies=4),
               "both": replace(base, gaze_mode="both", gaze_copies=4, gaze_target="params")}
    res = {}
    for name in only:
        if name in configs:
            sadm = fit_sadm(model, seq, tr, tex_tr, "krr", None, configs[name], seed)
            res[name] = {**score(sadm.synthesizer()), "alpha": None if sadm.gaze is None else sadm.gaze.alpha}
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dirs", nargs="+", required=True, help="ibug68+iris folders")
    ap.add_argument("--only", default=",".join(VARIANTS), help=f"comma-separated subset of {', '.join(VARIANTS)}")
    a = ap.parse_args()
    only = [v for v in a.only.split(",") if v]
    bad = set(only) - set(VARIANTS)
    if bad:
        raise SystemExit(f"unknown variants {sorted(bad)}")
    print(json.dumps({load_sequence(d).name: study(d, only) for d in a.dirs}))


if __name__ == "__main__":
    main()
