"""``facesynth codec``: geometry videos and the PDP codec.

Sub-subcommands::

    facesynth codec geometry OUT.npy [--frames 30 --size 256]   ICT mesh -> uint16 video (+ OUT.mask.npy)
    facesynth codec scan IN.npz|IN_*.obj OUT.npy --landmarks MAP.json   scans without UVs -> video
    facesynth codec encode IN.npy OUT.fsgv --qp N --modes hip|hip+pdp [--gop N]
    facesynth codec decode IN.fsgv OUT.npy
    facesynth codec rd [--input IN.npy] --qps 18,30,42,54 --plot rd.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from facesynth.errors import FacesynthError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    g = sub.add_parser("geometry", help="ICT face animated by blendshapes -> uint16 geometry video .npy")
    g.add_argument("output", type=Path)
    g.add_argument("--frames", type=int, default=30)
    g.add_argument("--size", type=int, default=256)
    g.add_argument("--seed", type=int, default=0)

    from facesynth.codec import scan_cli

    s = sub.add_parser("scan", help="face scans without UVs: fill holes, segment, parameterise (EIP) -> "
                       "uint16 geometry video .npy (+ .mask.npy, .scan.npz)")
    scan_cli.add_arguments(s)

    e = sub.add_parser("encode", help="encode a uint16 (T, H, W, 3) .npy geometry video")
    e.add_argument("input", type=Path)
    e.add_argument("output", type=Path)
    q = e.add_mutually_exclusive_group(required=True)
    q.add_argument("--qp", type=int, help="quantiser 0..87 (step x2 every 6)")
    q.add_argument("--lossless", action="store_true", help="transform bypass: exact reconstruction")
    _codec_options(e)
    e.add_argument("--mask", type=Path, help="(H, W) bool .npy: distortion counts only there "
                   "(default: IN.mask.npy when present)")

    d = sub.add_parser("decode", help="decode an .fsgv stream to a uint16 .npy")
    d.add_argument("input", type=Path)
    d.add_argument("output", type=Path)

    r = sub.add_parser("rd", help="sweep QPs over mode sets, print JSON, write an RD plot")
    r.add_argument("--input", type=Path, help="uint16 (T, H, W, 3) .npy (default: ICT blendshape video)")
    r.add_argument("--frames", type=int, default=8)
    r.add_argument("--size", type=int, default=256)
    r.add_argument("--qps", default="18,30,42,54")
    r.add_argument("--configs", default="hip-intra,hip+pdp-intra,hip+pdp+pvm",
                   help="comma list from facesynth.codec.rd.CONFIGS")
    r.add_argument("--block-sizes", default=None, help="comma list from 4, 8, 16 (default: 8,16 with "
                   "the 8x8 transform, else 4,8,16)")
    r.add_argument("--no-transform8", action="store_true", help="4x4 transform for every block size")
    r.add_argument("--plot", type=Path, default=Path("codec_rd.png"))
    r.add_argument("--json", type=Path, help="also write the figures here")


def _codec_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--modes", choices=["hip", "hip+pdp", "hip+pdp-spatial"], default="hip+pdp")
    p.add_argument("--gop", type=int, default=1, help="1 = all intra; N = I then N-1 P-frames")
    p.add_argument("--no-inter", action="store_true", help="P-frames without motion compensation")
    p.add_argument("--block-sizes", default=None, help="comma list from 4, 8, 16 (default: 8,16 with "
                   "the 8x8 transform, else 4,8,16)")
    p.add_argument("--no-transform8", action="store_true", help="4x4 transform for every block size")
    p.add_argument("--mv-range", type=int, default=2, help="full-search range in pixels")


def _sizes(text: str | None) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        out = tuple(int(s) for s in text.split(","))
    except ValueError:
        raise FacesynthError(f"--block-sizes: expected a comma list of 4, 8, 16, got {text!r}") from None
    return out


def _load_video(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FacesynthError(f"{path}: file not found")
    try:
        v = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error here
        raise FacesynthError(f"{path}: not a readable .npy file ({exc})") from None
    if v.ndim == 3:
        v = v[None]
    if v.ndim != 4 or v.dtype != np.uint16:
        raise FacesynthError(f"{path}: expected uint16 (T, H, W, C) or (H, W, C), got {v.dtype} {v.shape}")
    return v


def _load_mask(path: Path | None, video_path: Path, shape) -> np.ndarray | None:
    if path is None:
        auto = video_path.with_suffix(".mask.npy")
        if not auto.is_file():
            return None
        path = auto
    if not path.is_file():
        raise FacesynthError(f"--mask {path}: file not found")
    try:
        m = np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error here
        raise FacesynthError(f"--mask {path}: not a readable .npy file ({str(exc)[:120]})") from None
    if m.dtype.kind not in "biuf":
        raise FacesynthError(f"--mask {path}: expected a bool or numeric (H, W) array, got dtype {m.dtype}")
    if m.shape != tuple(shape):
        raise FacesynthError(f"{path}: mask shape {m.shape} does not match the video's {tuple(shape)}")
    return m.astype(bool)


def _ict_video(frames: int, size: int, seed: int):
    from facesynth.codec.geometry import build_layout, geometry_video
    from facesynth.codec.sources import ict_blendshape_sequence
    from facesynth.data.shared import shared_mesh_dir

    mdir = shared_mesh_dir()
    if mdir is None:
        raise FacesynthError("../shared/data/mesh is absent: pass --input IN.npy instead")
    s = ict_blendshape_sequence(mdir, frames, seed)
    lay = build_layout(s["faces"], s["uv"], size)
    vid, q = geometry_video(lay, s["frames"])
    return vid, lay.mask, q


def run(args: argparse.Namespace) -> int:
    from facesynth.codec.bitstream import decode_video, encode_video
    from facesynth.codec.frame import CodecConfig
    from facesynth.codec.rd import CONFIGS, bd_between, modes_config, plot_rd, rd_sweep
    from facesynth.io import check_writable, save_npy, write_bytes, write_json
    from facesynth.metrics import psnr

    if args.action == "scan":
        from facesynth.codec import scan_cli

        return scan_cli.run(args)
    if args.action in ("geometry", "encode", "decode"):
        check_writable(args.output)  # before the work
    if args.action == "geometry":
        vid, mask, q = _ict_video(args.frames, args.size, args.seed)
        save_npy(args.output, vid)
        save_npy(args.output.with_suffix(".mask.npy"), mask)
        print(json.dumps({"output": str(args.output), "shape": list(vid.shape), "mask_share": float(mask.mean()),
                          "bbox_lo": q.lo.tolist(), "bbox_hi": q.hi.tolist(), "diag": q.diag}))
        return 0
    if args.action == "encode":
        video = _load_video(args.input)
        mask = _load_mask(args.mask, args.input, video.shape[1:3])
        if args.gop < 1:
            raise FacesynthError(f"--gop: expected >= 1, got {args.gop}")
        cfg = CodecConfig(qp=None if args.lossless else args.qp, block_sizes=_sizes(args.block_sizes),
                          mv_range=args.mv_range, transform8=not args.no_transform8,
                          **modes_config(args.modes, args.gop, not args.no_inter))
        data, rec, st = encode_video(video, cfg, mask)
        write_bytes(args.output, data)
        st["psnr_db"] = psnr(video, rec, mask, peak=65535)
        st["psnr_db"] = None if not np.isfinite(st["psnr_db"]) else st["psnr_db"]
        st["encode_fps"] = len(video) / st.pop("encode_s")
        print(json.dumps({"output": str(args.output), **st}))
        return 0
    if args.action == "decode":
        if not args.input.is_file():
            raise FacesynthError(f"{args.input}: file not found")
        frames, info, st = decode_video(args.input.read_bytes())
        save_npy(args.output, frames)
        print(json.dumps({"output": str(args.output), "shape": list(frames.shape), "qp": info.qp,
                          "decode_fps": len(frames) / max(st["decode_s"], 1e-9)}))
        return 0
    # rd
    if args.input is not None:
        video = _load_video(args.input)
        mask = _load_mask(None, args.input, video.shape[1:3])
    else:
        video, mask, _ = _ict_video(args.frames, args.size, 0)
    names = args.configs.split(",")
    unknown = [n for n in names if n not in CONFIGS]
    if unknown:
        raise FacesynthError(f"--configs: unknown {unknown}; choose from {list(CONFIGS)}")
    qps = [int(q) for q in args.qps.split(",")]
    points = rd_sweep(video, mask, qps, {n: CONFIGS[n] for n in names},
                      CodecConfig(block_sizes=_sizes(args.block_sizes), transform8=not args.no_transform8))
    result = {"video_shape": list(video.shape), "qps": qps, "points": points,
              "bd_rate_vs_" + names[0]: {n: bd_between(points, names[0], n) for n in names[1:]}}
    plot_rd(points, args.plot, f"{video.shape[0]} frames {video.shape[1]}x{video.shape[2]}")
    result["plot"] = str(args.plot)
    if args.json:
        write_json(args.json, result)
    print(json.dumps(result))
    return 0
