"""Hydra callbacks: the run folder's lock (:class:`RunDirLock`, one ``train.py`` per folder)
and, after a sweep (``train.py -m``), one comparison table of all jobs (``comparison.md``,
``comparison.json``) and its plot beside it (``comparison.png``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from facesynth.errors import FacesynthError
from facesynth.io import write_json, write_text
from facesynth.runs.lock import lock_run_dir, release_run_dirs


def comparison_table(sweep_dir: str | Path) -> tuple[list[dict], str]:
    """Collect ``*/metrics.json`` under a sweep folder -> (rows, Markdown table)."""
    rows = []
    for path in sorted(Path(sweep_dir).glob("*/metrics.json")):
        m = json.loads(path.read_text())
        if "psnr_ref" not in m:
            continue
        row = {"job": path.parent.name, "regressor": m["regressor"], "features": m.get("features")}
        for key in ("psnr_ref", "psnr_frame", "psnr_train_ref"):
            for sigma, v in m.get(key, {}).get("sadm", {}).items():
                row[f"{key}@{sigma}"] = v
        row["mean_texture_ref@0"] = m["psnr_ref"]["mean_texture"].get("0")
        row["oracle_ref@0"] = m["psnr_ref"]["oracle"].get("0")
        row["ncc_mean"] = sum(m["ncc"]) / max(len(m["ncc"]), 1)
        rows.append(row)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    fmt = lambda v: f"{v:.2f}" if isinstance(v, float) else str(v)  # noqa: E731
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return rows, "\n".join(md) + "\n"


def comparison_plot(rows: list[dict], path: str | Path) -> None:
    """Bars of each job's test PSNR (sadm row, sigma 0) in the reference and the original frame,
    with the mean-texture floor and the oracle ceiling of the reference frame as markers."""
    import numpy as np

    from facesynth.eval.plots import pyplot, save

    plt = pyplot()
    labels = [f"{r['job']}\n{r['regressor']}" for r in rows]
    x = np.arange(len(rows))
    keys = [k for k in ("psnr_ref@0", "psnr_frame@0") if any(k in r for r in rows)]
    fig, ax = plt.subplots(figsize=(max(5.0, 1.3 * len(rows) + 2), 4.0))
    width = 0.8 / len(keys)
    for i, k in enumerate(keys):
        vals = [r.get(k, np.nan) for r in rows]
        bars = ax.bar(x + (i - (len(keys) - 1) / 2) * width, vals, width,
                      label={"psnr_ref@0": "sadm, reference frame", "psnr_frame@0": "sadm, original frame"}[k])
        ax.bar_label(bars, fmt="%.2f", fontsize=7)
    for k, marker, name in (("mean_texture_ref@0", "_", "mean_texture (floor), reference"),
                            ("oracle_ref@0", "_", "oracle (ceiling), reference")):
        vals = [r.get(k) if r.get(k) is not None else np.nan for r in rows]
        ax.scatter(x - (len(keys) - 1) / 2 * width, vals, marker=marker, s=400, lw=2, label=name, zorder=5)
    finite = [v for r in rows for k, v in r.items() if "@" in k and isinstance(v, float) and np.isfinite(v)]
    if finite:
        ax.set_ylim(min(finite) - 2, max(finite) + 1.5)
    ax.set_xticks(x, labels, fontsize=8)
    ax.set(ylabel="test PSNR at sigma 0 (dB)", title="sweep: test PSNR per job")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    save(fig, path)


class SweepTable(Callback):
    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        rows, md = comparison_table(sweep_dir)
        if rows:
            write_json(sweep_dir / "comparison.json", rows)
            comparison_plot(rows, sweep_dir / "comparison.png")
            write_text(sweep_dir / "comparison.md", md)
            print(f"\ncomparison of {len(rows)} runs -> {sweep_dir / 'comparison.md'} (plot: comparison.png)\n{md}")


class RunDirLock(Callback):
    """Locks the run folder before Hydra writes anything into it (``on_run_start``; a sweep's
    job folders in ``on_job_start``) and releases it when the run ends. A folder in use by
    another live ``train.py`` is one line ``error: ...`` and exit status 2."""

    @staticmethod
    def _lock(run_dir) -> None:
        try:
            lock_run_dir(str(run_dir))
        except FacesynthError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        self._lock(config.hydra.run.dir)

    def on_job_start(self, config: Any, **kwargs: Any) -> None:
        self._lock(config.hydra.runtime.output_dir)

    def on_job_end(self, config: Any, **kwargs: Any) -> None:
        release_run_dirs()
