"""Face scans without UVs -> geometry videos: figures for docs/codec.md (one JSON line).

Sections (ICT face from ../shared/data/mesh, its 53 blendshapes at weight 1 as the
"extreme expressions"):

- ``holes``: holes of several sizes punched into the ICT face and filled: RMS/max distance
  of the new vertices to the original surface (libigl point-mesh distance), crease angle
  across the loop against the same edges on the intact mesh, colour error (colour = position).
- ``segmentation``: share of the kept-vertex set that changes between neutral and each
  blendshape at a fixed radius, for several choices of source features (``SEGMENTATION_VARIANTS``),
  geodesic (heat; exact MMP for the default) against a Euclidean ball; the default at
  radius +-0.5.
- ``drift``: per-frame EIP and HM of neutral + 53 blendshapes; how far the same vertex moves
  in a ``size`` geometry image (the mesh's own UVs: 0 by construction, one fixed layout).
- ``codec``: an 8-frame blendshape animation as UV, EIP and HM geometry videos; RD sweep
  (IPPP with PDP+PVM), vertex PSNR over the face region and image PSNR over each
  video's mask (both against the sequence's bounding-box diagonal), BD-rates, and
  temporal coherence (MSE between consecutive frames after 8x8 block motion
  search, +-2 px).

Usage: ``OMP_NUM_THREADS=1 python -m bench.mesh.scan [--quick] [--plots DIR]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.harness import emit
from facesynth.codec.geometry import build_layout, geometry_video, sample_vertices
from facesynth.codec.rd import CONFIGS, bd_rate
from facesynth.codec.scan_cli import scan_geometry_video
from facesynth.codec.sources import blendshape_weights, load_ict_mesh
from facesynth.data.shared import shared_mesh_dir
from facesynth.landmarks import EYES, INNER_LIPS, JAW, MOUTH, NOSE, OUTER_EYE_CORNERS, RIGID_NOSE_EYES
from facesynth.mesh.holes import fill_holes, loop_crease_angles, punch_hole
from facesynth.mesh.laplacian import ordered_boundary_loops
from facesynth.mesh.scan import process_scan, uv_drift
from facesynth.mesh.segment import segment_face


def _landmarks(mdir: Path) -> np.ndarray:
    mp = json.loads((mdir / "ict_face_9409_ibug68_map.json").read_text())["map"]
    return np.array([mp[str(k)] for k in range(1, 69)], np.int64)


def bench_holes(m, lm) -> list[dict]:
    import igl

    V, F = m["vertices"], m["faces"]
    rim = np.concatenate(ordered_boundary_loops(F))
    out = []
    for where, centre in (("cheek", 1200), ("forehead", int(lm[19])), ("chin", int(lm[8])), ("nose", int(lm[30]))):
        for radius in (0.5, 1.0, 2.0):
            V1, F1, kept = punch_hole(V, F, centre, radius)
            t0 = time.perf_counter()
            fm = fill_holes(V1, F1, colors=V1, keep_open=np.nonzero(np.isin(kept, rim))[0])
            dt = time.perf_counter() - t0
            new = fm.vertices[fm.n_original:]
            d2, _, _ = igl.point_mesh_squared_distance(new, V, F)
            seam = np.concatenate([loop_crease_angles(fm.vertices, fm.faces, lp) for lp in fm.loops])
            ref = np.concatenate([loop_crease_angles(V, F, kept[lp]) for lp in fm.loops])
            out.append({"where": where, "radius_cm": radius, "loop_vertices": int(sum(len(lp) for lp in fm.loops)),
                        "new_vertices": int(len(new)), "rms_mm": 10 * float(np.sqrt(d2.mean())),
                        "max_mm": 10 * float(np.sqrt(d2.max())), "crease_mean_deg": float(seam.mean()),
                        "crease_max_deg": float(seam.max()), "intact_mean_deg": float(ref.mean()),
                        "intact_max_deg": float(ref.max()),
                        "colour_rms_mm": 10 * float(np.sqrt(((fm.colors[fm.n_original:] - new) ** 2).sum(1).mean())),
                        "fill_s": dt})
    return out


def _bridge_mouth(V: np.ndarray, F: np.ndarray, lm: np.ndarray):
    """The mesh with its mouth opening (the boundary loop nearest the inner-lip landmarks)
    closed by a fan to the loop's centroid: a variant in which geodesics may cross the mouth."""
    c = V[lm[list(INNER_LIPS)]].mean(0)
    lp = min(ordered_boundary_loops(F), key=lambda loop: np.linalg.norm(V[loop].mean(0) - c))
    fan = np.stack([lp, np.roll(lp, -1), np.full(len(lp), len(V))], 1)
    return np.vstack([V, V[lp].mean(0)]), np.vstack([F, fan])


# name -> (segment_face keywords, bridge the mouth); the first is segment_face's default
SEGMENTATION_VARIANTS = {
    "anchored (default)": (dict(sources="anchored"), False),
    "points (paper: eyes + mouth)": (dict(sources="points"), False),
    "contours": (dict(sources="contours"), False),
    "points, mouth bridged": (dict(sources="points"), True),
    "eye corners + nose": (dict(sources={"eyes_nose": (RIGID_NOSE_EYES, 1)}), False),
    "eyes + nose + mouth": (dict(sources={"all": (EYES + NOSE + MOUTH, 1)}), False),
    "eye corners + nose, mouth x2": (dict(sources={"eyes_nose": (RIGID_NOSE_EYES, 1), "mouth": (MOUTH, 2)}), False),
    "eye corners + nose, mouth x2, chin x1.5": (dict(sources={"eyes_nose": (RIGID_NOSE_EYES, 1), "mouth": (MOUTH, 2),
                                                              "chin": (JAW[7:10], 1.5)}), False),
}


def bench_segmentation(m, lm, names, shapes, radius: float, exact: bool = True) -> dict:
    """Kept-set change against neutral per blendshape, per variant and metric (before the
    eye/mouth cut); ``radius_sweep``: the default at radius +-0.5; ``inter_ocular``: the
    largest relative change of the outer eye-corner distance (what a per-frame radius
    normalisation would divide by); ``landmark_motion_cm``: displacement of a few landmarks
    under the mouth shapes."""
    V, F, B = m["vertices"], m["faces"], m["blendshapes"]

    def kept(Vt, kw, bridge, r=radius):
        Ft = F
        if bridge:
            Vt, Ft = _bridge_mouth(Vt, F, lm)
        k = segment_face(Vt, Ft, lm, r, remove_features=False, **kw).kept
        return set(k[k < len(V)].tolist())

    def change(kw, bridge=False, r=radius):
        base = kept(V, kw, bridge, r)
        ch = np.array([len(base ^ kept(V + B[k], kw, bridge, r)) / len(base) for k in shapes])
        worst = np.argsort(-ch)[:4]
        return {"kept": len(base), "mean_pct": 100 * float(ch.mean()), "median_pct": 100 * float(np.median(ch)),
                "max_pct": 100 * float(ch.max()), "within_1pct": int((ch <= 0.01).sum()), "of": len(ch),
                "worst": {names[shapes[i]]: round(100 * float(ch[i]), 2) for i in worst}}

    out = {}
    for label, (kw, bridge) in SEGMENTATION_VARIANTS.items():
        out[label] = {"geodesic_heat": change(dict(kw, metric="geodesic"), bridge),
                      "euclidean": change(dict(kw, metric="euclidean"), bridge)}
    default = next(iter(SEGMENTATION_VARIANTS))
    if exact:
        out[default]["geodesic_exact"] = change(dict(metric="geodesic", method="exact"))
    out["radius_sweep"] = {f"{r:g}": {"geodesic_heat": change(dict(metric="geodesic"), r=r),
                                      "euclidean": change(dict(metric="euclidean"), r=r)}
                           for r in (radius - 0.5, radius + 0.5)}
    io = [np.linalg.norm(np.subtract(*(V + (0 if k is None else B[k]))[lm[list(OUTER_EYE_CORNERS)]]))
          for k in (None, *shapes)]
    out["inter_ocular"] = {"neutral_cm": float(io[0]), "max_rel_change": float(np.max(np.abs(np.array(io) / io[0] - 1)))}
    # how far the lower lip (iBUG 58), the chin (iBUG 9) and the nose base (iBUG 34) move
    out["landmark_motion_cm"] = {names[k]: {f"ibug{i + 1}": round(float(np.linalg.norm(B[k][lm[i]])), 2) for i in (57, 8, 33)}
                                 for k in shapes if names[k] in ("jawOpen", "mouthClose", "mouthLeft", "mouthPucker")}
    return out


def bench_drift(m, lm, shapes, size: int, plots: Path | None) -> dict:
    V, F, B = m["vertices"], m["faces"], m["blendshapes"]
    out = {}
    for method in ("eip", "hm"):
        t0 = time.perf_counter()
        frames = [process_scan(V, F, lm, method=method)] + [process_scan(V + B[k], F, lm, method=method) for k in shapes]
        dt = (time.perf_counter() - t0) / len(frames)
        out[method] = {"all": uv_drift(frames, size), "beyond_3_rings_of_rim": uv_drift(frames, size, skip_rings=3),
                       "flipped_max": int(max(f.flipped for f in frames)),
                       "frames_with_flips": int(sum(f.flipped > 0 for f in frames)),
                       "untangled_max": int(max(f.untangled for f in frames)), "s_per_frame": dt}
        if plots is not None:
            _plot_layout(frames[0], plots / f"scan_{method}_layout.png", method.upper())
    out["own_uv"] = {"all": {"mean_px": 0.0, "p95_px": 0.0, "max_px": 0.0}, "note": "one fixed layout"}
    return out


def _plot_layout(fr, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    ax.triplot(fr.uv[:, 0], fr.uv[:, 1], fr.faces, lw=0.15, color="k")
    for name, col in (("eye_r", "tab:blue"), ("eye_l", "tab:green"), ("mouth", "tab:red"), ("outer", "tab:purple")):
        lp = np.r_[fr.loops[name], fr.loops[name][:1]]
        ax.plot(fr.uv[lp, 0], fr.uv[lp, 1], color=col, lw=1)
    ax.set_aspect("equal")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(f"{title}: ICT neutral, {len(fr.vertices)} vertices", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _coherence(video: np.ndarray, mask: np.ndarray, scale: float, r: int = 2, b: int = 8) -> float:
    """Mean squared error (mesh units^2) between each frame and the previous one after a
    full +-r block motion search per 8x8 block, over the mask."""
    v = video.astype(np.float64) * scale
    T, H, W, _ = v.shape
    hb, wb = H // b, W // b
    errs = []
    for t in range(1, T):
        cur, prev = v[t], np.pad(v[t - 1], ((r, r), (r, r), (0, 0)), mode="edge")
        best = np.full((hb, wb), np.inf)
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                sh = prev[r + dy:r + dy + H, r + dx:r + dx + W]
                e = (((cur - sh) ** 2).sum(-1) * mask)[:hb * b, :wb * b].reshape(hb, b, wb, b).sum((1, 3))
                best = np.minimum(best, e)
        errs.append(best.sum() / (3 * mask[:hb * b, :wb * b].sum()))
    return float(np.mean(errs))


def bench_codec(m, lm, size: int, n_frames: int, qps: list[int], plots: Path | None) -> dict:
    from dataclasses import replace

    from facesynth.codec.bitstream import decode_video, encode_video
    from facesynth.codec.frame import CodecConfig

    w = blendshape_weights(n_frames, len(m["blendshapes"]), seed=0)
    seq = m["vertices"][None] + np.einsum("tk,kvc->tvc", w, m["blendshapes"])
    diag = float(np.linalg.norm(seq.reshape(-1, 3).max(0) - seq.reshape(-1, 3).min(0)))
    faces = [m["faces"]] * n_frames
    videos = {}
    lay = build_layout(m["faces"], m["uv"], size)
    vid, q = geometry_video(lay, seq)
    videos["uv"] = (vid, lay.mask, q, [lay] * n_frames, [np.arange(len(m["vertices"]))] * n_frames)
    for method in ("eip", "hm"):
        vid, mask, q, frames, lays = scan_geometry_video(list(seq), faces, np.broadcast_to(lm, (n_frames, 68)),
                                                         size, method=method)
        videos[method] = (vid, mask, q, lays, [fr.source for fr in frames])
    # vertices compared: those of the EIP face region in each frame (all sources >= 0 there)
    region = [src[src >= 0] for src in videos["eip"][4]]
    out, points = {}, {}
    cfg0 = replace(CodecConfig(), **CONFIGS["hip+pdp+pvm-ippp"])
    for name, (vid, mask, q, lays, srcs) in videos.items():
        pts = []
        for qp in qps:
            data, rec, _ = encode_video(vid, replace(cfg0, qp=qp), mask)
            dec, _, _ = decode_video(data)
            assert np.array_equal(dec, rec)
            err = []
            for t in range(n_frames):
                pos = np.full(len(m["vertices"]), -1)
                pos[srcs[t][srcs[t] >= 0]] = np.nonzero(srcs[t] >= 0)[0]
                got = sample_vertices(lays[t], q.dequantise(dec[t]))[pos[region[t]]]
                err.append(np.linalg.norm(got - seq[t][region[t]], axis=1))
            err = np.concatenate(err)
            de = (dec.astype(np.float64) - vid) * (q.diag / 65535)  # image error in mesh units
            img_rmse = np.sqrt((de ** 2).sum(-1)[:, mask].mean() / 3)
            pts.append({"qp": qp, "bits_per_frame": 8 * len(data) / n_frames,
                        "vertex_psnr_db": float(20 * np.log10(diag / np.sqrt((err ** 2).mean()))),
                        "image_psnr_db": float(20 * np.log10(diag / max(img_rmse, 1e-12))),
                        "vertex_mean_mm": 10 * float(err.mean())})
        points[name] = pts
        out[name] = {"mask_share": float(mask.mean()), "points": pts,
                     "coherence_mse_mm2": 100 * _coherence(vid, mask, q.diag / 65535)}
    for key in ("vertex_psnr_db", "image_psnr_db"):
        bd = {}
        for a, b in (("uv", "eip"), ("uv", "hm"), ("hm", "eip")):
            pa, pb = points[a], points[b]
            bd[f"{b}_vs_{a}"] = bd_rate([p["bits_per_frame"] for p in pa], [p[key] for p in pa],
                                        [p["bits_per_frame"] for p in pb], [p[key] for p in pb])
        out["bd_rate_" + key[:-3]] = bd
    out["frames"], out["size"], out["diag_cm"], out["config"] = n_frames, size, diag, "hip+pdp+pvm-ippp"
    if plots is not None:
        _plot_videos(videos, plots / "scan_geometry_images.png")
    return out


def _plot_videos(videos, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 3, figsize=(10, 3.6))
    for ax, (name, (vid, mask, *_)) in zip(axs, videos.items(), strict=True):
        img = vid[0].astype(float) / 65535
        img = (img - img[mask].min(0)) / np.ptp(img[mask], axis=0)
        ax.imshow(np.clip(img, 0, 1) * mask[..., None])
        ax.set_title(f"{name.upper()} (x, y, z as RGB)", fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8 blendshapes, 4 frames, 3 QPs")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--radius", type=float, default=6.0)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--qps", default="42,54,60,66,72")
    ap.add_argument("--plots", type=Path, help="write PNGs here")
    ap.add_argument("--sections", default="holes,segmentation,drift,codec")
    args = ap.parse_args(argv)
    mdir = shared_mesh_dir()
    if mdir is None:
        print(json.dumps({"skipped": "../shared/data/mesh is absent"}))
        return 0
    if args.plots:
        args.plots.mkdir(parents=True, exist_ok=True)
    m = load_ict_mesh(mdir)
    lm = _landmarks(mdir)
    names = json.loads((mdir / "ict_face_9409_blendshape_names.json").read_text())
    shapes = list(range(len(names)))
    if args.quick:
        shapes = [names.index(n) for n in ("jawOpen", "mouthSmile_L", "eyeBlink_R", "browInnerUp_L", "mouthPucker",
                                            "cheekPuff_L", "mouthClose", "mouthLeft")]
    qps = [int(x) for x in args.qps.split(",")][: 3 if args.quick else None]
    sections = args.sections.split(",")
    res: dict = {"radius_cm": args.radius, "size": args.size, "blendshapes": len(shapes)}
    t0 = time.perf_counter()
    if "holes" in sections:
        res["holes"] = bench_holes(m, lm)
    if "segmentation" in sections:
        res["segmentation"] = bench_segmentation(m, lm, names, shapes, args.radius, exact=not args.quick)
    if "drift" in sections:
        res["drift"] = bench_drift(m, lm, shapes, args.size, args.plots)
    if "codec" in sections:
        res["codec"] = bench_codec(m, lm, args.size, 4 if args.quick else args.frames, qps, args.plots)
    res["total_s"] = time.perf_counter() - t0
    emit(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
