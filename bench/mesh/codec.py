"""Benchmark of geometry videos and the PDP codec; prints ONE JSON line.

    python -m bench.mesh.codec [--frames 10 --size 256 --qps 18,30,42,54,60,66,72]
                                             [--no-anchors] [--plot codec_rd.png] [--quick]

Source: the ICT face (9409 vertices, ../shared/data/mesh) animated by seeded blendshape
curves, rasterised over its UVs and quantised to 16 bits (shared scale, bounding box
stored). Everything is measured here: geometry rasterisation rate and round-trip error,
RD points of our codec under several mode sets (bits = real bitstream bytes, PSNR peak
65535 over the mask), BD-rates (common PSNR range stated), mode-usage shares, encode and
decode frames/s at 256 and 512, and ffmpeg anchors when ffmpeg is installed.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from bench.harness import emit, load_average
from facesynth.codec.bitstream import decode_video, encode_video  # noqa: E402
from facesynth.codec.frame import CodecConfig  # noqa: E402
from facesynth.codec.geometry import (  # noqa: E402
    build_layout,
    geometry_video,
    rasterise,
    sample_vertices,
    vertex_solver,
)
from facesynth.codec.rd import CONFIGS, bd_between, bd_rate, plot_rd, rd_sweep  # noqa: E402
from facesynth.codec.sources import ict_blendshape_sequence  # noqa: E402
from facesynth.data.shared import shared_mesh_dir  # noqa: E402
from facesynth.provenance import array_fingerprint, package_versions  # noqa: E402


def geometry_figures(seq: dict, sizes=(256, 512)) -> dict:
    out = {}
    frames = seq["frames"]
    diag = float(np.linalg.norm(frames.reshape(-1, 3).max(0) - frames.reshape(-1, 3).min(0)))
    for s in sizes:
        t0 = time.perf_counter()
        lay = build_layout(seq["faces"], seq["uv"], s)
        t_layout = time.perf_counter() - t0
        t0 = time.perf_counter()
        img = rasterise(lay, frames)
        fps = len(frames) / (time.perf_counter() - t0)
        err = np.linalg.norm(sample_vertices(lay, img) - frames, axis=-1)
        vid, q = geometry_video(lay, frames[:3])
        err16 = np.linalg.norm(sample_vertices(lay, q.dequantise(vid)) - frames[:3], axis=-1)
        t0 = time.perf_counter()
        solver = vertex_solver(lay)
        t_factor = time.perf_counter() - t0
        t0 = time.perf_counter()
        ls = np.linalg.norm(solver(q.dequantise(vid)) - frames[:3], axis=-1)
        t_solve = (time.perf_counter() - t0) / 3
        out[str(s)] = {"layout_s": t_layout, "rasterise_fps": fps, "mask_share": float(lay.mask.mean()),
                       "round_trip_err_cm": {"mean": float(err.mean()), "median": float(np.median(err)),
                                             "p99": float(np.quantile(err, 0.99)), "max": float(err.max())},
                       "round_trip_err_16bit_cm_mean": float(err16.mean()),
                       "least_squares_16bit_err_cm": {"mean": float(ls.mean()), "median": float(np.median(ls)),
                                                      "p99": float(np.quantile(ls, 0.99)), "max": float(ls.max()),
                                                      "factorise_s": t_factor, "solve_s_per_frame": t_solve}}
    out["mesh_bbox_diag_cm"] = diag
    return out


def speed(video_by_size: dict, qp: int, repeats: int = 3) -> dict:
    """Encode/decode frames/s: the best of ``repeats`` runs (the machine is shared), with
    the 1-minute load average before the runs."""
    out = {"load_average_1min": load_average(), "repeats": repeats}
    for s, (vid, mask) in video_by_size.items():
        for name, sizes in (("hip+pdp-intra", (8, 16)), ("hip+pdp-intra", (4, 8, 16)),
                            ("hip+pdp+pvm-ippp", (8, 16)), ("hip+pdp+pvm-ippp", (4, 8, 16))):
            cfg = CodecConfig(qp=qp, block_sizes=sizes, **CONFIGS[name])
            enc_s, dec_s = [], []
            for _ in range(repeats):
                data, rec, st = encode_video(vid, cfg, mask)
                enc_s.append(st["encode_s"])
                t0 = time.perf_counter()
                dec, _, _ = decode_video(data)
                dec_s.append(time.perf_counter() - t0)
            out[f"{name}@{s} blocks {','.join(map(str, sizes))}"] = {
                "frames": len(vid), "qp": qp, "encode_fps": len(vid) / min(enc_s), "decode_fps": len(vid) / min(dec_s),
                "encode_fps_median": len(vid) / float(np.median(enc_s)), "decode_fps_median": len(vid) / float(np.median(dec_s)),
                "bit_exact": bool(np.array_equal(dec, rec))}
    return out


def anchors(vid, mask, x264_qps, x265_qps, j2k_levels) -> dict:
    import codec_anchors as ca

    have = ca.available()
    if not have:
        return {"skipped": "ffmpeg is not installed"}
    res = {"ffmpeg_encoders": have, "cap_10bit_db": ca.depth_cap(vid, mask, 10),
           "cap_12bit_db": ca.depth_cap(vid, mask, 12)}

    def sweep(key, codec, bits, qs, intra):
        try:
            res[key] = [ca.code(vid, mask, codec, bits, q, intra) for q in qs]
        except RuntimeError as exc:
            res[key] = {"error": str(exc)}

    if have.get("libx264"):
        sweep("x264-10bit-444-intra", "libx264", 10, x264_qps, True)
        sweep("x264-10bit-444-ippp", "libx264", 10, x264_qps, False)
    if have.get("libx265"):
        sweep("x265-12bit-444-ippp", "libx265", 12, x265_qps, False)
    if have.get("ffv1"):
        sweep("ffv1-16bit-lossless", "ffv1", 16, [None], True)
    if have.get("libopenjpeg"):
        sweep("jpeg2000-16bit", "libopenjpeg", 16, j2k_levels, True)
    return res


def compare(points: dict, ours: str, anchor_pts: list, below: float | None) -> dict:
    """BD-rate of our config against an anchor (negative: ours needs fewer bits)."""
    if not isinstance(anchor_pts, list):
        return {"bd_rate_pct": None}
    a = [p for p in anchor_pts if p["psnr_db"] is not None and (below is None or p["psnr_db"] <= below)]
    o = [p for p in points[ours] if below is None or p["psnr_db"] <= below + 3]
    if len(a) < 2 or len(o) < 2:
        return {"bd_rate_pct": None, "note": "fewer than 2 points in range"}
    out = bd_rate([p["bits_per_frame"] for p in a], [p["psnr_db"] for p in a],
                  [p["bits_per_frame"] for p in o], [p["psnr_db"] for p in o])
    out["anchor_psnr_limit_db"] = below
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--qps", default="18,30,42,48,54,60,66,72")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--speed-qp", type=int, default=48)
    ap.add_argument("--no-anchors", action="store_true")
    ap.add_argument("--plot", type=Path, default=None, help="write the RD plot PNG here")
    ap.add_argument("--quick", action="store_true", help="4 frames, 4 QPs, no 512 speed run")
    ap.add_argument("--speed-only", action="store_true", help="only the encode/decode frames/s figures")
    ap.add_argument("--speed-repeats", type=int, default=3, help="best of this many speed runs")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.qps = 4, "30,42,54,66"
    mdir = shared_mesh_dir()
    if mdir is None:
        print(json.dumps({"skipped": "../shared/data/mesh is absent"}))
        return
    seq = ict_blendshape_sequence(mdir, args.frames, seed=0)
    result = {"bench": "codec", "source": f"ICT 9409-vertex face, blendshape animation (seed 0), "
              f"{args.frames} frames", "threads": os.environ.get("OMP_NUM_THREADS", "unset"),
              "versions": package_versions()}
    lay = build_layout(seq["faces"], seq["uv"], args.size)
    vid, q = geometry_video(lay, seq["frames"])
    mask = lay.mask
    if args.speed_only:
        lay5 = build_layout(seq["faces"], seq["uv"], 512)
        v5, _ = geometry_video(lay5, seq["frames"][:3])
        result["speed"] = speed({args.size: (vid[:6], mask), 512: (v5, lay5.mask)}, args.speed_qp, args.speed_repeats)
        emit(result)
        return
    result["geometry"] = geometry_figures(seq, (args.size,) if args.quick else (256, 512))
    result["video"] = {"shape": list(vid.shape), "fingerprint": array_fingerprint(vid),
                       "bbox_diag_cm": q.diag, "mask_share": float(mask.mean())}
    qps = [int(x) for x in args.qps.split(",")]
    names = args.configs.split(",")
    t0 = time.perf_counter()
    points = rd_sweep(vid, mask, qps, {n: CONFIGS[n] for n in names})
    result["rd_sweep_s"] = time.perf_counter() - t0
    result["rd"] = {n: [{k: p[k] for k in ("qp", "bits_per_frame", "bpp", "psnr_db", "bit_exact")} for p in pts]
                    for n, pts in points.items()}
    result["mode_share"] = {n: {str(p["qp"]): p["mode_share"] for p in pts} for n, pts in points.items()}
    bd = {}
    pairs = [("hip-intra", "hip+pdp-intra"), ("hip+pdp-intra", "hip+pdp+pvm"), ("hip-intra", "hip+pdp+pvm"),
             ("hip-ippp", "hip+pdp+pvm-ippp")]
    for a, b in pairs:
        if a in points and b in points:
            bd[f"{b} vs {a}"] = bd_between(points, a, b)
            bd[f"{b} vs {a} (>=65 dB)"] = bd_between(points, a, b, min_psnr=65.0)
    result["bd_rate"] = bd
    if not args.no_anchors:
        an = anchors(vid, mask, [0, 6, 12, 18, 24, 30, 36], [0, 6, 12, 18, 24, 30], [0, 3, 6, 12, 24, 48])
        result["anchors"] = an
        if "cap_10bit_db" in an:
            lim = an["cap_10bit_db"] - 3.0
            result["vs_anchors"] = {
                "hip+pdp-intra vs x264-10bit-444-intra": compare(points, "hip+pdp-intra",
                                                                 an.get("x264-10bit-444-intra"), lim),
                "hip+pdp+pvm-ippp vs x264-10bit-444-ippp": compare(points, "hip+pdp+pvm-ippp",
                                                                   an.get("x264-10bit-444-ippp"), lim),
                "hip+pdp+pvm-ippp vs x265-12bit-444-ippp": compare(points, "hip+pdp+pvm-ippp",
                                                                   an.get("x265-12bit-444-ippp"), None),
                "hip+pdp-intra vs jpeg2000-16bit": compare(points, "hip+pdp-intra", an.get("jpeg2000-16bit"), None),
            }
    lossless = encode_video(vid, CodecConfig(qp=None, **CONFIGS["hip+pdp-intra"]), mask)
    result["lossless"] = {"bits_per_frame": 8 * len(lossless[0]) / len(vid),
                          "exact": bool(np.array_equal(decode_video(lossless[0])[0], vid))}
    lossless_p = encode_video(vid, CodecConfig(qp=None, **CONFIGS["hip+pdp+pvm-ippp"]), mask)
    result["lossless"]["ippp_bits_per_frame"] = 8 * len(lossless_p[0]) / len(vid)
    sizes = {args.size: (vid[:6], mask)}
    if not args.quick:
        lay5 = build_layout(seq["faces"], seq["uv"], 512)
        v5, _ = geometry_video(lay5, seq["frames"][:3])
        sizes[512] = (v5, lay5.mask)
    result["speed"] = speed(sizes, args.speed_qp, args.speed_repeats)
    if args.plot:
        pts = dict(points)
        for k, v in (result.get("anchors") or {}).items():
            if isinstance(v, list) and len(v) > 1:
                pts[k] = [p for p in v if p["psnr_db"] is not None]
        plot_rd(pts, args.plot, f"ICT geometry video {vid.shape[0]}x{vid.shape[1]}x{vid.shape[2]}")
        result["plot"] = str(args.plot)
    emit(result)
if __name__ == "__main__":
    main()
