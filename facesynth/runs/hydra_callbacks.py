"""Hydra callback: after a sweep (``train.py -m``), one comparison table of all jobs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from facesynth.io import write_json, write_text


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


class SweepTable(Callback):
    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        rows, md = comparison_table(sweep_dir)
        if rows:
            write_json(sweep_dir / "comparison.json", rows)
            write_text(sweep_dir / "comparison.md", md)
            print(f"\ncomparison of {len(rows)} runs -> {sweep_dir / 'comparison.md'}\n{md}")
