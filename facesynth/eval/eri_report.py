"""Report of an ERI run (``train.py model=eri``): ``report.md`` + self-contained
``report.html`` with plots, beside the tables of ``eri_report.md`` (written by the eri stage)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.eval.document import Document
from facesynth.eval.plots import pyplot, save

ROWS = {
    "eps_linear": "epsilon-SVR, linear kernel, one per eigenERI coefficient (FAPs -> coefficient)",
    "eps_rbf": "epsilon-SVR, RBF kernel",
    "nu_linear": "nu-SVR, linear kernel",
    "nu_rbf": "nu-SVR, RBF kernel",
    "sadm_NAME": "a SADM regressor (facesynth.regressors) on standardised FAPs, for comparison",
    "val MSE": "mean squared error on the validation slice (end of the training segment), standardised coefficients: "
               "what the automatic driver choice uses",
    "variance explained": "1 - total squared error / total variance of the coefficients on the test frames",
    "geometry": "(a) the neutral frame warped to the test frame's landmarks (no expression details)",
    "eri": "(b) geometry + expression ratio image from the FAPs by the driver (what transfer uses)",
    "eri_raw": "(b') as (b) without edge confidence / brightening cap",
    "eri_true_coefficients": "(c) ERI with the true (projected) coefficients: the ceiling of the driving model",
}


def _coefficients_plot(m: dict, path) -> None:
    plt = pyplot()
    table = m["coefficients"]
    names = list(table)
    ev = [table[n]["explained_variance"] for n in names]
    driver = m["model"]["driver"]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * len(names) + 2), 3.8))
    colors = ["tab:orange" if n == driver else "tab:blue" for n in names]
    bars = ax.bar(np.arange(len(names)), ev, color=colors)
    ax.bar_label(bars, labels=[f"{v:.2f}" + (f"\nval {table[n]['val_mse']:.2f}" if table[n].get("val_mse") is not None else "")
                               for n, v in zip(names, ev, strict=True)], fontsize=7)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(np.arange(len(names)), names, fontsize=8)
    lo = min(-0.1, min(ev) - 0.15)
    ax.set(ylim=(lo, 1.05), ylabel="test variance explained",
           title=f"driving model: test variance explained per regressor (orange: driver {driver})")
    ax.grid(axis="y", alpha=0.3)
    save(fig, path)


def _r2_plot(m: dict, path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.6))
    for name, row in m["coefficients"].items():
        r2 = row.get("r2_per_coefficient")
        if r2:
            ax.plot(np.arange(1, len(r2) + 1), r2, marker=".", lw=1, label=name)
    ax.set(xlabel="eigenERI coefficient (1 = most variance)", ylabel="r^2 (test)", ylim=(-0.02, 1.02),
           title="squared correlation of predicted vs true coefficients, per coefficient")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=3)
    save(fig, path)


def _synthesis_plot(m: dict, path) -> None:
    plt = pyplot()
    p = m["synthesis"]["psnr_db"]
    names = list(p)
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    bars = ax.bar(np.arange(len(names)), [p[n] for n in names], color=["tab:gray", "tab:orange", "tab:blue", "tab:green"])
    ax.bar_label(bars, fmt="%.2f", fontsize=8)
    ax.set_xticks(np.arange(len(names)), names, fontsize=8)
    vals = [v for v in p.values() if np.isfinite(v)]
    ax.set(ylim=(min(vals) - 2, max(vals) + 1), ylabel="PSNR over the face mask (dB)",
           title=f"same-subject synthesis, {m['synthesis']['frames']} test frames")
    ax.grid(axis="y", alpha=0.3)
    save(fig, path)


def write_eri_report(m: dict, out_dir: str | os.PathLike, plot_dir: str = "plots") -> Document:
    """Plots and ``report.md`` / ``report.html`` of an ERI run's metrics (``eri_metrics.json``)."""
    d = Path(out_dir)
    (d / plot_dir).mkdir(parents=True, exist_ok=True)
    plots = {"eri_coefficients.png": (_coefficients_plot, "Test variance explained of the eigenERI coefficients per "
                                      "regressor; labels give the validation MSE used to choose the driver (orange)."),
             "eri_r2_per_coefficient.png": (_r2_plot, "Per-coefficient r^2 on the test frames for every regressor."),
             "eri_synthesis.png": (_synthesis_plot, "PSNR of same-subject synthesis: geometry only, ERI, raw ERI, "
                                   "ERI with the true coefficients.")}
    doc = Document(f"ERI run on {m['sequence']}")
    choice = m["model"].get("driver_choice", {})
    doc.bullets([f"frames: {m['train_frames']} train / {m['test_frames']} test (temporal split)",
                 f"neutral frame: row {m['neutral']['row']} ({m['neutral'].get('rule', '')})",
                 f"{m['model']['n_components']} eigenERIs keep {100 * m['model']['variance_kept']:.1f}% of the variance",
                 f"driver: {m['model']['driver']}" + (f" ({choice['rule']})" if choice else ""),
                 f"training took {m['train_seconds']:.1f} s"])
    doc.heading("Legend")
    doc.table(["row / column", "meaning"], [[k, v] for k, v in ROWS.items()])
    doc.heading("Driving model: eigenERI coefficients from FAPs (test frames)")
    doc.table(["regressor", "val MSE", "MSE", "normalised MSE", "r^2 (mean)", "variance explained"],
              [[n, "-" if r.get("val_mse") is None else f"{r['val_mse']:.3f}", f"{r['mse']:.4g}", f"{r['nmse']:.3f}",
                f"{r['r2']:.3f}", f"{r['explained_variance']:.3f}"] for n, r in m["coefficients"].items()])
    doc.heading("Same-subject synthesis (PSNR over the face mask, dB)")
    doc.table(["method", "PSNR (dB)"], [[k, f"{v:.2f}"] for k, v in m["synthesis"]["psnr_db"].items()])
    doc.heading("Plots")
    for name, (fn, caption) in plots.items():
        fn(m, d / plot_dir / name)
        doc.figure(f"{plot_dir}/{name}", caption)
    doc.write(d)
    return doc
