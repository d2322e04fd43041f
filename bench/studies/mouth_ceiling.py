"""How far a predictor from landmarks can take the mouth, on trained runs; one JSON line.

    OMP_NUM_THREADS=1 python -m bench.studies.mouth_ceiling RUN [RUN ...] [--modes refit,best8] \
        [--today DIR]

Each RUN is a ``facesynth train`` run (video data), evaluated held out as
``bench/studies/perceptual.py`` reports it (sigma 0, test landmarks smoothed as the default
does, the face pasted into the real frame), in each mode:

* ``refit``: the run's regressor (its settings) refitted with the *test* frames' textures among
  its training rows: what this regressor class gets from the landmarks of frames it has seen;
* ``bestK`` (e.g. ``best8``): among the K training frames nearest in the regressor's features,
  the one whose texture is nearest the test frame's own in the mouth (lips and interior) puts
  its real texture there (feathered), the prediction elsewhere: the best any retrieval of one
  of the subject's own frames could do, chosen knowing the answer.

Per run and mode, one line on stderr with ``lpips_face``, ``lpips_mouth``,
``psnr_frame_common`` and the rest of ``bench.studies.perceptual.metric_figures``; the last line
(stdout) holds them all, with ``--today DIR`` (``DIR/CLIP__today``) the median change of the mouth
LPIPS per mode against today's prediction, beside the run's own prediction and its PCA oracle.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from bench.harness import emit
from bench.studies.landmark_smoothing import run_sequence
from bench.studies.perceptual import figures, metric_figures
from facesynth.eval.common_region import common_landmarks
from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
from facesynth.landmarks import get_scheme
from facesynth.sadm.fit import SADM, fit_sadm, load_sadm
from facesynth.sadm.regions import reference_regions
from facesynth.sadm.synthesis import Synthesizer


def mouth_weight(model) -> np.ndarray:
    """(M,) the lips and interior of the reference frame, feathered (2 % of its width), in [0, 1]."""
    samp, reg = model.sampler(), reference_regions(model)
    m = np.zeros(samp.n_pixels, np.float32)
    for part in ("mouth_interior", "lips"):
        if part in reg:
            m[reg[part]] = 1.0
    img = samp.to_image(torch.from_numpy(m).reshape(1, 1, -1), 0.0)[0, 0].numpy()
    img = np.clip(cv2.GaussianBlur(img, (0, 0), 0.02 * img.shape[1]) * 1.5, 0, 1)
    return img.reshape(-1)[samp.mask_index.numpy()]


class BestOfK(Synthesizer):
    """The synthesiser whose mouth is the test frame's best match among its K nearest training
    frames (``truth``: the test frames' textures, keyed by their landmarks' bytes)."""

    def setup(self, sadm, k, feats, textures, truth, weight):
        self.k, self.sadm, self.feats, self.textures, self.truth, self.weight = k, sadm, feats, textures, truth, weight
        return self

    def _texture(self, landmarks):
        tex = super()._texture(landmarks)
        lm = landmarks.numpy()
        f, c, w = self.sadm.features(lm), self.sadm.model.n_channels, torch.from_numpy(self.weight)
        for b in range(len(lm)):
            true = self.truth.get(lm[b].tobytes())
            if true is None:
                continue
            near = np.argsort(np.linalg.norm(self.feats - f[b], axis=1))[: self.k]
            cand = self.textures[near].reshape(len(near), c, -1)
            err = (((cand - true.reshape(c, -1)) ** 2) * self.weight).sum((1, 2))
            tex[b] = tex[b] * (1 - w) + torch.from_numpy(cand[int(np.argmin(err))]) * w
        return tex


@dataclasses.dataclass
class BestOfKSADM(SADM):
    """The SADM whose synthesiser is :class:`BestOfK` (``oracle``: its ``setup`` arguments)."""

    oracle: tuple = ()

    def synthesizer(self) -> BestOfK:
        syn = BestOfK(self.model, self.appearance(), self.config.clamp_shape, self.scheme).eval()
        return syn.setup(*self.oracle)


def best_k(mode: str) -> int | None:
    """K of a ``bestK`` mode (K >= 1); None for any other mode."""
    k = mode[4:] if mode.startswith("best") else ""
    return int(k) if k.isdigit() and int(k) > 0 else None


def evaluate(run: Path, modes: list[str]) -> dict:
    """Each mode's figures on ``run`` (modes checked by :func:`main`: ``refit`` or ``bestK``)."""
    sadm = load_sadm(run)
    cfg, seq, tr, te, _ = run_sequence(run, True)
    model = sadm.model
    model_seq = seq.to_scheme(get_scheme(seq.scheme).base_scheme().name)
    ecfg = EvalConfig(noise=[0.0], train_level=False, talking_head=False)
    common = common_landmarks(seq, None)
    tex_tr, tex_te = model.sample_textures(model_seq, tr), model.sample_textures(model_seq, te)
    out = {}
    for mode in modes:
        if mode == "refit":
            params = {k: v for k, v in sadm.regressor_config.items() if k != "info"}
            s = fit_sadm(model, seq, np.concatenate([tr, te]), np.concatenate([tex_tr, tex_te]), sadm.name, params,
                         sadm.config, int(cfg.seed))
        else:
            truth = {seq.landmarks[r].tobytes(): tex_te[i] for i, r in enumerate(te)}
            oracle = (sadm, best_k(mode), sadm.features(seq.landmarks[tr]), tex_tr, truth, mouth_weight(model))
            s = BestOfKSADM(**{f.name: getattr(sadm, f.name) for f in dataclasses.fields(SADM)}, oracle=oracle)
        with torch.no_grad():
            metrics, _ = evaluate_sadm(s, seq, tr, te, ecfg, int(cfg.seed), test_textures=tex_te, common=common)
        fig = metric_figures(metrics)
        fig.pop("lpips_ceiling", None)
        out[mode] = fig
        print(json.dumps({"run": run.name, "mode": mode, **fig}), file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--modes", default="refit,best8", help="comma-separated: refit, bestK (default refit,best8)")
    ap.add_argument("--today", type=Path, default=None, help="DIR holding CLIP__today runs: report changes against them")
    args = ap.parse_args()
    modes = [m for m in args.modes.split(",") if m]
    bad = [m for m in modes if m != "refit" and best_k(m) is None]
    if bad or not modes:
        ap.error(f"--modes: unknown mode(s) {bad} (refit, bestK with K >= 1)")
    runs = {run.name: {"run": figures(run), **evaluate(run, modes)} for run in args.runs}
    result = {"runs": runs}
    if args.today is not None:
        change = {}
        for name, fig in runs.items():
            base = args.today / f"{name.split('__')[0]}__today"
            if not (base / "metrics.json").is_file():
                continue
            t = figures(base)["lpips_mouth"]
            row = {m: fig[m]["lpips_mouth"] / t - 1 for m in ("run", *modes)}
            row["oracle"] = fig["run"]["lpips_ceiling"]["mouth"]["oracle"] / t - 1
            change[name] = row
        result["mouth_change_median"] = {m: float(np.median([c[m] for c in change.values()]))
                                         for m in ("run", *modes, "oracle")} if change else None
        result["clips"] = len(change)
    emit(result)


if __name__ == "__main__":
    main()
