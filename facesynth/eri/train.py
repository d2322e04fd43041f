"""Training and evaluation of an ERI model on one subject (``python train.py model=eri``).

:func:`train_eri` takes the run's temporal split (``data.train_fraction``, ``data.gap``),
fits :class:`EriModel`, and writes into ``out_dir``:

* ``eri/`` - the model artifact (``EriModel.save``);
* ``eri_metrics.json`` - every figure below, the config, package versions, fingerprint;
* ``eri_report.md`` - the tables: the paper's Fig. 5 (epsilon/nu-SVR x linear/RBF: MSE and
  squared correlation coefficient r^2 of the predicted eigenERI coefficients on the test
  frames, plus any SADM regressors for comparison) and same-subject synthesis PSNR over
  the face mask for (a) geometry-only warp of the neutral frame, (b) ERI from FAPs, and
  (c) ERI with the true (projected) coefficients, an upper bound for the driving model.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from facesynth.data.sequence import FaceSequence
from facesynth.data.splits import temporal_split
from facesynth.eri.config import SVR_VARIANTS, EriConfig
from facesynth.eri.driving import coefficient_scores
from facesynth.eri.faps import head_pose
from facesynth.eri.model import EriModel
from facesynth.eri.synthesis import EriSynthesizer
from facesynth.io import write_json, write_text
from facesynth.progress import bar as progress_bar
from facesynth.progress import stage
from facesynth.provenance import package_versions
from facesynth.regressors import REGISTRY

log = logging.getLogger(__name__)


def train_eri(cfg, seq: FaceSequence, out_dir, seed: int = 0,
              split: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Train, evaluate and write an ERI run.

    Parameters
    ----------
    cfg : EriConfig, dict or OmegaConf node (the ``eri`` group)
    seq : FaceSequence with frames
    out_dir : path of the run directory (created)
    seed : fixes every random choice (SADM comparison regressors; libsvm is deterministic)
    split : (train rows, test rows) of ``seq``; default :func:`temporal_split` with its defaults

    Returns
    -------
    dict
        The metrics written to ``eri_metrics.json``.
    """
    cfg = EriConfig.from_dict(cfg)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    np.random.seed(seed)
    torch.manual_seed(seed)
    train, test = temporal_split(len(seq)) if split is None else (np.asarray(split[0]), np.asarray(split[1]))
    t0 = time.perf_counter()
    with stage("ERI model fit") as st:
        model = EriModel.fit(seq, train, cfg, progress=True)
        st.set(f"{len(train)} training frames, {model.pca.n_components} eigenERIs, driver {model.driver}")
    train_s = time.perf_counter() - t0

    true = model.pca.project(model.ratios_of(seq, test).reshape(len(test), -1))
    faps = model.faps(seq.landmarks[test])
    table = {}
    for v in SVR_VARIANTS:
        table[v] = {**coefficient_scores(model.regressors[v].predict(faps), true),
                    "support_vectors": int(len(model.regressors[v].sv)),
                    "val_mse": model.meta["regressors"][v]["val_mse"], "params": model.meta["regressors"][v]["params"]}
    with stage("ERI comparison regressors"):
        table.update(_compare(cfg, model, faps, true, seed))
    with stage("ERI synthesis evaluation"):
        synthesis = evaluate_synthesis(model, seq, test, true, cfg.eval_frames)
    metrics = {
        "sequence": seq.name, "frames": len(seq), "train_frames": int(len(train)), "test_frames": int(len(test)),
        "seed": seed, "model": model.describe(), "neutral": model.meta["neutral"], "train_seconds": train_s,
        "fit_seconds": model.meta["fit_seconds"], "coefficients": table, "synthesis": synthesis,
        "config": cfg.to_dict(), "data_fingerprint": seq.fingerprint, "packages": package_versions(),
    }
    model.save(out / "eri", {"split": {"train": [0, int(len(train))], "test": [int(test[0]), int(test[-1]) + 1]}})
    write_json(out / "eri_metrics.json", metrics)
    write_text(out / "eri_report.md", report_markdown(metrics))
    return metrics


def _compare(cfg: EriConfig, model: EriModel, faps: np.ndarray, true: np.ndarray, seed: int) -> dict:
    """SADM regressors named in ``cfg.compare`` on standardised FAPs (absent names are skipped)."""
    x, y = model.training["faps"], model.training["coefficients"]
    mu, sd = x.mean(0), x.std(0) + 1e-8
    n_val = max(1, int(round(len(x) * cfg.val_fraction)))
    out = {}
    for name in cfg.compare:
        cls = REGISTRY.get(name)
        if cls is None:
            log.info("eri: SADM regressor %r is not in this build; skipped", name)
            continue
        z = (x - mu) / sd
        reg = cls.fit(z[:-n_val], y[:-n_val], None, z[-n_val:], y[-n_val:], seed=seed)
        out[f"sadm_{name}"] = {**coefficient_scores(reg.predict((faps - mu) / sd), true), **reg.summary()}
    return out


def evaluate_synthesis(model: EriModel, seq: FaceSequence, rows, true_coeffs: np.ndarray, max_frames: int = 0) -> dict:
    """Same-subject synthesis of test ``rows`` from their FAPs on the model's neutral frame,
    placed in each test frame's head pose; PSNR over the rendered face mask (pooled over
    frames) against the real frame, for the geometry-only warp, ERI and ERI with the true
    coefficients (``true_coeffs`` (len(rows), K))."""
    rows = np.asarray(rows)
    pick = np.arange(len(rows))
    if max_frames and len(rows) > max_frames:
        pick = np.linspace(0, len(rows) - 1, max_frames).round().astype(int)
    syn = EriSynthesizer(model, seq.frame(model.neutral_index), model.neutral_landmarks)
    raw = EriSynthesizer(model, seq.frame(model.neutral_index), model.neutral_landmarks, raw=True)
    sse = {"geometry": 0.0, "eri": 0.0, "eri_raw": 0.0, "eri_true_coefficients": 0.0}
    per_frame = {k: [] for k in sse}
    count = 0
    t_render = 0.0
    for s in progress_bar(range(0, len(pick), model.config.batch_size), desc="ERI synthesis", unit="batch"):
        p = pick[s : s + model.config.batch_size]
        r = rows[p]
        bg = seq.load_frames(r)
        faps = model.faps(seq.landmarks[r])
        poses = head_pose(seq.landmarks[r], model.neutral_landmarks)
        t = time.perf_counter()
        geo, mask = syn.render(faps, "geometry", bg, poses, feather=0)
        eri, _ = syn.render(faps, "eri", bg, poses, feather=0)
        t_render += time.perf_counter() - t
        eri_raw, _ = raw.render(faps, "eri", bg, poses, feather=0)
        orc, _ = raw.render(faps, "eri", bg, poses, coefficients=true_coeffs[p], feather=0)
        m = mask[..., None].repeat(3, -1)
        count += int(m.sum())
        for k, img in (("geometry", geo), ("eri", eri), ("eri_raw", eri_raw), ("eri_true_coefficients", orc)):
            err = (img.astype(np.float64) - bg) ** 2 * m
            sse[k] += float(err.sum())
            per_frame[k] += [_psnr(e.sum() / max(mm.sum(), 1)) for e, mm in zip(err, m, strict=True)]
    res = {k: _psnr(v / max(count, 1)) for k, v in sse.items()}
    gain = np.array(per_frame["eri"]) - np.array(per_frame["geometry"])
    return {
        "psnr_db": res, "eri_gain_db": res["eri"] - res["geometry"], "eri_raw_gain_db": res["eri_raw"] - res["geometry"],
        "per_frame_gain_db": {"median": float(np.median(gain)), "p10": float(np.percentile(gain, 10)),
                              "fraction_positive": float((gain > 0).mean())},
        "frames": int(len(pick)), "mask_pixels_per_frame": count / 3 / max(len(pick), 1),
        "seconds_per_frame_geometry_plus_eri": t_render / max(len(pick), 1),
    }


def _psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else float(10 * np.log10(255.0**2 / mse))


def report_markdown(m: dict) -> str:
    """The Markdown tables of a metrics dict from :func:`train_eri`."""
    lines = [
        f"# ERI on {m['sequence']}: {m['train_frames']} training / {m['test_frames']} test frames (temporal split)",
        "",
        f"Neutral frame: row {m['neutral']['row']} ({m['neutral'].get('rule', '')}); "
        f"{m['model']['n_components']} eigenERIs keep {100 * m['model']['variance_kept']:.1f}% of the variance; "
        f"synthesis driver: {m['model']['driver']}. Training took {m['train_seconds']:.1f} s.",
        "",
        "## Driving model (cf. the paper's Fig. 5): eigenERI coefficients predicted from FAPs, test frames",
        "",
        "MSE in coefficient units (mean over coefficients); normalised MSE divides each by its test variance; "
        "r^2 is the squared correlation coefficient; variance explained = 1 - total squared error / total variance.",
        "",
        "| regressor | MSE | normalised MSE | r^2 (mean) | r^2 (first 5) | variance explained | support vectors |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, row in m["coefficients"].items():
        lines.append(f"| {name} | {row['mse']:.4g} | {row['nmse']:.3f} | {row['r2']:.3f} | {row['r2_first5']:.3f} | "
                     f"{row['explained_variance']:.3f} | "
                     f"{row.get('support_vectors', '-')} |")
    s = m["synthesis"]
    p = s["psnr_db"]
    lines += [
        "",
        f"## Same-subject synthesis from FAPs ({s['frames']} test frames, PSNR over the face mask, pooled)",
        "",
        "| method | PSNR (dB) |",
        "|---|---:|",
        f"| (a) geometry-only warp of the neutral frame | {p['geometry']:.2f} |",
        f"| (b) ERI, coefficients from FAPs ({m['model']['driver']}), as used for transfer | {p['eri']:.2f} |",
        f"| (b') ERI, coefficients from FAPs, raw ratios (no edge confidence / brightening cap) | {p['eri_raw']:.2f} |",
        f"| (c) ERI, true coefficients, raw ratios (upper bound of the driving model) | {p['eri_true_coefficients']:.2f} |",
        "",
        f"ERI gain over geometry-only: {s['eri_gain_db']:+.2f} dB pooled (raw ratios {s['eri_raw_gain_db']:+.2f} dB); "
        "per frame (b) median "
        f"{s['per_frame_gain_db']['median']:+.2f} dB, better on {100 * s['per_frame_gain_db']['fraction_positive']:.0f}% of frames.",
        "",
    ]
    return "\n".join(lines)
