"""The batch's summary: ``summary.csv``, ``summary.md``, ``summary.json`` and ``summary.png``
(held-out PSNR per subject against the mean-texture baseline and the PCA oracle)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from facesynth.io import atomic_path, write_json, write_text

#: One row per subject. psnr_* are held-out reference-frame PSNR (dB) at landmark noise sigma 0.
COLUMNS = (
    "subject", "status", "ran", "reason", "frames", "face_frames", "train_frames", "test_frames", "regressor",
    "psnr_sadm", "psnr_mean_texture", "psnr_oracle", "export_bytes",
    "ingest_s", "train_s", "evaluate_s", "export_s", "wall_s", "peak_rss_mb", "video",
)


def flat_row(row: dict) -> dict:
    """A job's row with its stage times flattened into the COLUMNS."""
    flat = {k: v for k, v in row.items() if k != "times"}
    flat.update(row.get("times", {}))
    return {c: flat.get(c) for c in COLUMNS}


def _fmt(col: str, v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.1f}" if col.endswith(("_s", "_mb")) else f"{v:.2f}"
    return str(v).replace("\n", " ")


def counts(rows: list[dict]) -> dict:
    return {s: sum(r["status"] == s for r in rows) for s in ("ok", "skipped", "failed")}


def markdown(rows: list[dict]) -> str:
    flat = [flat_row(r) for r in rows]
    cols = [c for c in COLUMNS if c != "video"]
    c = counts(rows)
    lines = [
        f"# Batch summary: {len(rows)} subjects",
        "",
        (f"{c['ok']} trained now, {c['skipped']} already complete (skipped), {c['failed']} failed. "
        "PSNR: held-out reference-frame PSNR in dB (landmark noise 0) of the SADM, the mean-texture "
        "baseline and the PCA oracle; times in seconds (of the run that did each stage); "
        "peak_rss_mb: peak memory of the process that ran the subject."),
        "",
        "| " + " | ".join(cols) + " |",
        "|" + "---|" * len(cols),
    ]
    for r in flat:
        lines.append("| " + " | ".join(_fmt(k, r[k]).replace("|", "/") for k in cols) + " |")
    return "\n".join(lines) + "\n"


#: Above this many subjects the plot sorts them by SADM PSNR and drops their names.
PLOT_NAMED_MAX = 40


def plot(rows: list[dict], path: Path) -> Path:
    """Held-out PSNR per subject: SADM against the mean texture and the oracle (the grey bar
    spans baseline -> oracle). Many subjects: sorted by SADM PSNR, drawn as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if r.get("psnr_sadm") is not None and r["status"] != "failed"]
    failed = [r["subject"] for r in rows if r["status"] == "failed"]
    many = len(done) > PLOT_NAMED_MAX
    if many:
        done = sorted(done, key=lambda r: r["psnr_sadm"])
    fig, ax = plt.subplots(figsize=(10.0 if many else max(5.0, 0.7 * len(done) + 2.5), 4.2))
    x = list(range(len(done)))
    series = {k: [r[k] for r in done] for k in ("psnr_sadm", "psnr_mean_texture", "psnr_oracle")}
    label = f"SADM ({done[0]['regressor']})" if done else "SADM"
    if many:
        ax.fill_between(x, series["psnr_mean_texture"], series["psnr_oracle"], color="0.85", step="mid", lw=0)
        ax.plot(x, series["psnr_mean_texture"], ".", ms=3, color="tab:gray", label="mean texture")
        ax.plot(x, series["psnr_oracle"], ".", ms=3, color="tab:green", label="PCA oracle")
        ax.plot(x, series["psnr_sadm"], "-", color="tab:blue", label=label)
        ax.set_xlabel("subjects, sorted by SADM PSNR")
    else:
        for i, r in enumerate(done):
            ax.plot([i, i], [r["psnr_mean_texture"], r["psnr_oracle"]], color="0.8", lw=6, solid_capstyle="round", zorder=1)
        ax.scatter(x, series["psnr_mean_texture"], marker="_", s=300, color="tab:gray", label="mean texture", zorder=2)
        ax.scatter(x, series["psnr_oracle"], marker="^", s=50, color="tab:green", label="PCA oracle", zorder=2)
        ax.scatter(x, series["psnr_sadm"], marker="o", s=50, color="tab:blue", label=label, zorder=3)
        ax.set_xlim(-0.7, max(len(done), 1) - 0.3)
        ax.set_xticks(x)
        tilt = len(done) > 6
        ax.set_xticklabels([r["subject"] for r in done], rotation=45 if tilt else 0, ha="right" if tilt else "center")
    ax.set_ylabel("held-out PSNR (dB), landmark noise 0")
    title = f"{len(done)} subjects"
    if failed:
        title += f"; {len(failed)} failed: {', '.join(failed[:6])}{' ...' if len(failed) > 6 else ''}"
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    if done:
        ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return path


def write_summary(rows: list[dict], out_dir: Path) -> dict[str, Path]:
    """Write the summary files into ``out_dir``; returns {kind: path}."""
    out_dir = Path(out_dir)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(flat_row(r) for r in rows)
    paths = {"csv": out_dir / "summary.csv", "md": out_dir / "summary.md", "json": out_dir / "summary.json",
             "png": out_dir / "summary.png"}
    write_text(paths["csv"], buf.getvalue())
    write_text(paths["md"], markdown(rows))
    write_json(paths["json"], [flat_row(r) for r in rows])
    plot(rows, paths["png"])
    return paths
