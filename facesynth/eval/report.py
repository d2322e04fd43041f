"""Evaluation reports of a SADM run: ``report.md`` and a self-contained ``report.html`` plus
the plots in ``plots/`` (:mod:`facesynth.eval.plots`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.eval import plots as P
from facesynth.eval.document import Document
from facesynth.eval.strip import write_strip
from facesynth.landmarks import FACE_REGIONS

# What each row and column of the tables (and of the console summary) means.
ROWS = {
    "sadm": "the trained model: appearance predicted from the landmarks alone",
    "mean_texture": "no model: the mean appearance warped to the landmarks (the floor)",
    "oracle": "the frame's true texture projected on the appearance PCA (the ceiling of any landmarks->appearance "
              "mapping with this PCA)",
    "rewarp": "the frame's own texture sampled into the reference frame and warped back (the loss of resampling "
              "alone; original-frame table only)",
}
COLUMNS = {
    "s0..s3 / sigma k": "Gaussian noise of k frame pixels added to the test landmarks (the target stays the clean frame)",
    "ncc": "per-component normalised cross-correlation of predicted vs true appearance parameters b_g (test frames)",
}

PLOTS = {
    "psnr_vs_noise.png": "Test PSNR against landmark noise for every row, in the reference frame and in the original frame.",
    "psnr_over_time.png": "Per-frame test PSNR across the test segment (sigma 0); red circles mark the worst frames.",
    "test_grid.png": "Evenly spaced test frames: real, synthesized from the landmarks, and their amplified difference; "
                     "titles give the frame number and its PSNR over the face region.",
    "motion_strip.png": "The face moving: consecutive held-out frames (sigma 0), real (top) and synthesized from the "
                        "landmarks, pasted into the real frame with blend_face (bottom); one frame box for all.",
    "talking_head_strip.png": "The talking head: held-out frames (top) and the avatar driving itself through the whole "
                              "talking head (retargeted landmarks, the synthesised face in its own frame warped with "
                              "the head; bottom); one head box for all.",
    "error_map.png": "Mean squared error of the synthesized test textures per reference pixel (sigma 0).",
    "ncc.png": "Per-component NCC of predicted vs true appearance parameters; red bars are negative.",
}


def write_plots(metrics: dict, extras: dict, out_dir: str | os.PathLike) -> list[str]:
    """Write every plot the data allows into ``out_dir``; returns the file names written."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    written = []
    P.psnr_vs_noise(metrics, d / "psnr_vs_noise.png")
    written.append("psnr_vs_noise.png")
    if extras.get("per_frame") is not None:
        extras["worst_frames"] = P.psnr_over_time(extras["per_frame"], d / "psnr_over_time.png")
        written.append("psnr_over_time.png")
    if extras.get("grid"):
        P.test_grid(extras["grid"], d / "test_grid.png")
        written.append("test_grid.png")
    if extras.get("strip"):
        write_strip(extras["strip"], d / "motion_strip.png")
        written.append("motion_strip.png")
    if extras.get("talking_head_strip"):
        write_strip(extras["talking_head_strip"], d / "talking_head_strip.png")
        written.append("talking_head_strip.png")
    if extras.get("err_map") is not None:
        P.error_map(extras["err_map"], d / "error_map.png")
        written.append("error_map.png")
    if metrics.get("ncc"):
        P.ncc_bars(metrics["ncc"], d / "ncc.png")
        written.append("ncc.png")
    return written


def _table(doc: Document, block: dict) -> None:
    keys = list(next(iter(block.values())).keys())
    doc.table(["row"] + [f"sigma {k}" for k in keys], [[name] + [f"{row[k]:.2f}" for k in keys] for name, row in block.items()])


def below_mean(metrics: dict, noise: str = "0") -> list[str]:
    """'part (where): sadm x dB < mean texture y dB' for every face part whose held-out PSNR at
    landmark noise ``noise`` is below the mean texture's, in the reference frame
    (``psnr_ref_regions``) and over the common region (``psnr_frame_common_regions``)."""
    out = []
    for key, where in (("psnr_ref_regions", "reference frame"), ("psnr_frame_common_regions", "frame, common region")):
        for part, rows in (metrics.get(key) or {}).items():
            s, m = rows.get("sadm", {}).get(noise), rows.get("mean_texture", {}).get(noise)
            if s is not None and m is not None and s < m:
                out.append(f"{part} ({where}): sadm {s:.2f} dB < mean texture {m:.2f} dB")
    return out


def _region_table(doc: Document, block: dict | None, digits: int, title: str) -> None:
    """One table of a per-region figure ({region: {row: value}}), under ``title``; nothing when absent."""
    if not block:
        return
    doc.heading(title, 3)
    names = list(next(iter(block.values())))
    doc.table(["region"] + names, [[reg] + [f"{v[n]:.{digits}f}" for n in names] for reg, v in block.items()])


def face_detail_sections(doc: Document, metrics: dict) -> None:
    """The report's per-part figures: the per-part reference-frame PSNR, the SADM's shrinkage
    weights, the sharpness, LPIPS and flicker tables (the parts below the mean texture are on
    the first screen, :func:`weak_regions`)."""
    if metrics.get("psnr_ref_regions"):
        doc.heading("Test PSNR in the reference frame per face part (dB)", 3)
        rows = metrics["psnr_ref_regions"]
        keys = list(next(iter(rows.values()))["sadm"])
        doc.table(["part"] + [f"{r} sigma {k}" for r in ("sadm", "mean_texture") for k in keys],
                  [[p] + [f"{v[r][k]:.2f}" for r in ("sadm", "mean_texture") for k in keys] for p, v in rows.items()])
    shrink = metrics.get("region_shrink")
    if shrink:
        how = f"{shrink['folds']}-fold blocked cross-validation" if shrink.get("folds") else "the validation slice"
        doc.heading(f"Shrinkage towards the mean texture per face part ({how}, {shrink['val_frames']} training frames "
                    "scored held out; val = those frames)", 3)
        doc.table(["part", "weight", "val sadm dB", "val mean texture dB", "val shrunk dB"],
                  [[p, f"{w:.2f}"] + [f"{shrink['psnr'][p][r]:.2f}" for r in ("sadm", "mean_texture", "shrunk")]
                   for p, w in shrink["weights"].items()])
    _region_table(doc, metrics.get("sharpness_frame_common"), 2,
                  "Sharpness over the common region (rendered / real Sobel gradient energy, median over frames, "
                  "sigma 0; 1 = as detailed as the real frame)")
    _region_table(doc, metrics.get("lpips_frame_common"), 4,
                  "Perceptual distance LPIPS-Alex of the face pasted into the real frame (median over frames, sigma 0; "
                  "lower is closer, 0 = the real frame)")
    fl = metrics.get("flicker_frame_common")
    if fl:
        doc.heading(f"Flicker: the face's mean absolute frame-to-frame change on {fl['frames']} consecutive held-out frames "
                    "(0-255; ratio to the real frames')", 3)
        rows = [r for r in fl["ratio"]]
        doc.table(["", "real"] + rows, [["change", f"{fl['real']:.2f}"] + [f"{fl[r]:.2f}" for r in rows],
                                        ["ratio", "1.00"] + [f"{fl['ratio'][r]:.2f}" for r in rows]])


def _row(name: str) -> str:
    """A row's name as a reader reads it: ``mean_texture`` -> ``mean texture``, ``rewarp`` -> ``re-warp``."""
    return name.replace("_", " ").replace("rewarp", "re-warp")


def verdict_lines(metrics: dict) -> list[str]:
    """One line per measure for the report's first screen: held-out PSNR against the mean
    texture and the oracle (original frame and reference frame), the perceptual distance and
    the sharpness where measured, and the talking head's figures."""
    lines = []
    for key, where in (("psnr_frame", "original frame, face region"), ("psnr_ref", "reference frame, face mask")):
        rows = metrics.get(key)
        if not rows or "0" not in rows.get("sadm", {}):
            continue
        s, m, o = rows["sadm"]["0"], rows["mean_texture"]["0"], rows["oracle"]["0"]
        verdict = "learned" if s > m else "NOT LEARNED (no better than the mean texture)"
        lines.append(f"Held-out PSNR ({where}, sigma 0): {verdict}: {s:.2f} dB, {s - m:+.2f} dB over the mean texture "
                     f"({m:.2f}), {o - s:.2f} dB below the oracle ({o:.2f}).")
    lp = metrics.get("lpips_frame_common") or {}
    if "sadm" in lp.get("face", {}):
        parts = ", ".join(f"{reg} {v['sadm']:.3f}" for reg, v in lp.items() if "sadm" in v)
        bounds = ", ".join(f"the {_row(r)}'s {v:.3f}" for r, v in lp["face"].items() if r != "sadm")
        lines.append(f"Perceptual distance (LPIPS-Alex, lower is closer, 0 = the real frame): {parts}"
                     + (f"; on the face, {bounds}." if bounds else "."))
    else:
        lines.append("Perceptual distance (LPIPS): not measured (the perceptual extra is not installed).")
    sharp = (metrics.get("sharpness_frame_common") or {})
    part = sharp.get("whole") or next(iter(sharp.values()), None)
    if part and "sadm" in part:
        others = ", ".join(f"{_row(r)} {v:.2f}" for r, v in part.items() if r != "sadm")
        lines.append(f"Sharpness (rendered / real gradient energy, 1 = as detailed as the real frame): {part['sadm']:.2f}"
                     + (f" ({others})." if others else "."))
    else:
        lines.append("Sharpness: not measured (no common face region: the clip's dlib points are not known).")
    head = metrics.get("talking_head")
    if head:
        f, st, w = head["full"], head["static"], head["warp"]
        better = "better than" if f["psnr_head_db"] > st["psnr_head_db"] else "NOT better than"
        lines.append(f"Talking head, driving itself on {head['frames']} held-out frames: head PSNR {f['psnr_head_db']:.2f} dB, "
                     f"SSIM {f['ssim_head']:.3f}, {better} its still neutral frame ({st['psnr_head_db']:.2f} dB) and "
                     f"{f['psnr_head_db'] - w['psnr_head_db']:+.2f} dB over the warp alone ({w['psnr_head_db']:.2f}).")
    else:
        lines.append("Talking head: not measured (eval.talking_head=false, or a clip without frames).")
    return lines


def weak_regions(metrics: dict, worst_frames: list[int] | None = None) -> list[str]:
    """The first screen's weak regions: every face part below the mean texture (flagged), then
    each part's held-out gain over the mean texture and gap to the oracle, weakest first, and
    the worst test frames."""
    out = [f"WARNING, worse than rendering no model: {flag}." for flag in below_mean(metrics)]
    parts = {p: rows for p, rows in (metrics.get("psnr_frame_common_regions") or {}).items() if p != "whole"}
    where = "frame, common region"
    if not parts:
        parts, where = metrics.get("psnr_ref_regions") or {}, "reference frame"
    gains = []
    for p, rows in parts.items():
        s, m = rows.get("sadm", {}).get("0"), rows.get("mean_texture", {}).get("0")
        if s is not None and m is not None:
            o = rows.get("oracle", {}).get("0")
            gains.append((s - m, f"{p.replace('_', ' ')} {s:.2f} dB ({s - m:+.2f} over the mean texture"
                                 + (f", {o - s:.2f} below the oracle)" if o is not None else ")")))
    if gains:
        out.append(f"Face parts, weakest first ({where}, sigma 0): " + "; ".join(t for _, t in sorted(gains)) + ".")
    if not below_mean(metrics):
        out.insert(0, "No face part is below the mean texture.")
    if worst_frames:
        out.append(f"Worst test frames (reference-frame PSNR, sigma 0): {', '.join(map(str, worst_frames))}.")
    return out


def legend_lines() -> list[str]:
    """The legend of rows and columns, one line each (console and reports)."""
    return [f"{k}: {v}" for k, v in {**ROWS, **COLUMNS}.items()]


def write_report(metrics: dict, out_dir: str | os.PathLike, plots: list[str], header: dict | None = None,
                 plot_dir: str = "plots", worst_frames: list[int] | None = None) -> Document:
    """Write ``report.md`` and ``report.html`` summarising ``metrics`` with the plots.

    The first screen holds the verdict line per measure (:func:`verdict_lines`), the real |
    rendered strip and the weak regions (:func:`weak_regions`); every table and plot follows in
    collapsible sections."""
    doc = Document(f"facesynth run: {metrics.get('regressor')} regressor")
    doc.bullets(verdict_lines(metrics), "verdict")
    strip = next((p for p in ("motion_strip.png", "test_grid.png") if p in plots), None)
    if strip:
        doc.figure(f"{plot_dir}/{strip}", PLOTS[strip])
    doc.heading("Weak regions")
    doc.bullets(weak_regions(metrics, worst_frames))

    doc.open_section("Run")
    lines = [f"{k}: {v}" for k, v in (header or {}).items()]
    lines += [f"shape components: {metrics['n_shape']}, appearance components: {metrics['n_appearance']}",
              f"frames: {metrics['train_frames']} train / {metrics['test_frames']} test (temporal split)"]
    fl = metrics.get("frame_level_frames")
    if fl:
        lines.append(f"original-frame PSNR measured on {fl['evaluated']} of {fl['test_frames']} test frames, evenly spaced "
                     f"(eval.max_test_frames={fl['max_test_frames']})")
    doc.bullets(lines)
    doc.heading("Legend", 3)
    doc.table(["row / column", "meaning"], [[k, v] for k, v in {**ROWS, **COLUMNS}.items()])
    doc.close_section()

    doc.open_section("Held-out PSNR tables")
    doc.heading("Test PSNR in the reference frame (dB, peak 255, over the face mask)", 3)
    _table(doc, metrics["psnr_ref"])
    if "psnr_frame" in metrics:
        doc.heading("Test PSNR in the original frame (dB, whole pipeline, face region)", 3)
        _table(doc, metrics["psnr_frame"])
    common = metrics.get("psnr_frame_common_regions", {})
    for region, table in common.items():
        doc.heading(f"Test PSNR in the original frame over the common region, {region} (dB; dlib hull 0-26 eroded 3 px)", 3)
        _table(doc, table)
    unseen = [p.replace("_", " ") for p in FACE_REGIONS if common and p not in common]
    if unseen:
        doc.para(f"Not in any evaluated frame, so not measured: {', '.join(unseen)} (a closed mouth has no interior).")
    if "psnr_train_ref" in metrics:
        doc.heading("Training-frame PSNR in the reference frame (the paper's Table 2 setting)", 3)
        _table(doc, metrics["psnr_train_ref"])
    doc.close_section()

    doc.open_section("Face parts, sharpness, perceptual distance and flicker")
    face_detail_sections(doc, metrics)
    doc.close_section()

    head = metrics.get("talking_head")
    if head:
        doc.open_section(f"Talking head: the avatar driving itself on {head['frames']} held-out frames")
        doc.para(f"Relative motion, neutral = training frame {head['neutral_row']}. "
                 "static: the avatar's neutral frame unchanged; warp: that frame warped with the landmarks, no "
                 "synthesised face; full: the synthesised face composited into the warped frame (what the exported "
                 "talking head renders). Head region: the real landmarks' hull grown to hair and neck."
                 + (f" The warp's head ring: {head['ring_scale']:g} x the default size, chosen on the training frames."
                    if "ring_scale" in head else ""))
        doc.table(["renderer", "head PSNR (dB)", "head SSIM", "frame PSNR (dB)", "frame SSIM"],
                  [[r] + [f"{head[r][k]:.2f}" if k.startswith("psnr") else f"{head[r][k]:.3f}"
                          for k in ("psnr_head_db", "ssim_head", "psnr_frame_db", "ssim_frame")]
                   for r in ("static", "warp", "full")])
        if "outline" in head:
            o = head["outline"]
            doc.para(f"The warp's grid along the head's outline (jaw, hair, neck), against the exact piecewise affine "
                     f"warp: its map {o['map_px_p99']:.2f} px off (99th percentile; {o['map_px_max']:.2f} px at most), "
                     f"staircase energy {o['staircase']:.4f} of the edges' (0: none).")
        doc.close_section()

    ncc = np.asarray(metrics.get("ncc", []))
    if ncc.size:
        doc.open_section("Appearance parameters: per-component NCC of predicted vs true b_g (test frames)")
        doc.para(f"first 10: {', '.join(f'{v:.2f}' for v in ncc[:10])}; mean over all {ncc.size}: {ncc.mean():.3f}; "
                 f"range {ncc.min():.2f} .. {ncc.max():.2f}")
        doc.close_section()
    st = metrics.get("reference_stretch")
    if st:
        doc.open_section("Reference stretch (test frames)")
        doc.para(f"The render stretches the reference frame's most stretched triangle {st['median']:.1f} times in area on "
                 f"the median test frame ({st['p99']:.1f} at the 99th percentile, {st['max']:.1f} at most); a part "
                 f"stretched past about 5 times shows its few reference pixels as streaks (model.reference_area_quantile).")
        doc.close_section()
    rest = [p for p in plots if p != strip]
    if rest:
        doc.open_section("Plots")
        for p in rest:
            doc.figure(f"{plot_dir}/{p}", PLOTS.get(p, p))
        doc.close_section()
    doc.write(out_dir)
    return doc
