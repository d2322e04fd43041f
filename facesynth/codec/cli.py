"""``facesynth codec``: geometry videos and the PDP codec.

Sub-subcommands::

    facesynth codec geometry OUT.npy [--frames 30 --size 256]   ICT mesh -> uint16 video (+ OUT.mask.npy)
    facesynth codec scan IN.npz|IN_*.obj OUT.npy --landmarks MAP.json   scans without UVs -> video
    facesynth codec encode IN.npy|SEQ.npz OUT.fsgv --qp N --modes hip|hip+pdp [--gop N] [--preview P.png]
    facesynth codec decode IN.fsgv OUT.npy | --mesh OUT.npz [--preview P.png --reference IN]
    facesynth codec rd [--input IN.npy] --qps 18,30,42,54 --plot rd.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from facesynth import progress
from facesynth.errors import FacesynthError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    g = sub.add_parser("geometry", help="ICT face animated by blendshapes -> uint16 geometry video .npy")
    g.add_argument("output", type=Path, help="output .npy: uint16 (T, H, W, 3) geometry video (+ OUTPUT.mask.npy)")
    g.add_argument("--frames", type=int, default=30, help="number of frames (default 30)")
    g.add_argument("--size", type=int, default=256, help="geometry image side in pixels (default 256)")
    g.add_argument("--seed", type=int, default=0, help="seed of the blendshape weight curves (default 0)")

    from facesynth.codec import scan_cli

    s = sub.add_parser("scan", help="face scans without UVs: fill holes, segment, parameterise (EIP) -> "
                       "uint16 geometry video .npy (+ .mask.npy, .scan.npz)")
    scan_cli.add_arguments(s)

    e = sub.add_parser("encode", help="encode a uint16 (T, H, W, 3) .npy geometry video or a transfer3d .npz mesh sequence")
    e.add_argument("input", type=Path, help="uint16 (T, H, W, 3) .npy geometry video, or a transfer3d output .npz "
                   "(vertices, faces, uvs): rasterised to a geometry video over its UV layout first")
    e.add_argument("output", type=Path, help="output .fsgv stream (from a mesh sequence also OUTPUT.layout.npz)")
    q = e.add_mutually_exclusive_group(required=True)
    q.add_argument("--qp", type=int, help="quantiser 0..87 (step x2 every 6)")
    q.add_argument("--lossless", action="store_true", help="transform bypass: exact reconstruction")
    _codec_options(e)
    e.add_argument("--mask", type=Path, help="(H, W) bool .npy: distortion counts only there "
                   "(default: IN.mask.npy when present; a mesh sequence's own UV mask)")
    e.add_argument("--size", type=int, default=256, help="geometry image side for a mesh sequence input (default 256)")
    e.add_argument("--preview", type=Path, metavar="PNG",
                   help="write the first frame's decoded geometry image beside the original and their error")

    d = sub.add_parser("decode", help="decode an .fsgv stream to a uint16 .npy (or a mesh sequence with --mesh)")
    d.add_argument("input", type=Path, help=".fsgv stream")
    d.add_argument("output", type=Path, help="output .npy geometry video, or .npz mesh sequence with --mesh")
    d.add_argument("--mesh", action="store_true", help="give the mesh sequence back (vertices, faces, uvs .npz; needs "
                   "the layout sidecar written by encode)")
    d.add_argument("--layout", type=Path, help="layout sidecar (default: INPUT.layout.npz)")
    d.add_argument("--preview", type=Path, metavar="PNG", help="write the first decoded frame beside --reference and "
                   "their error")
    d.add_argument("--reference", type=Path, help="the original .npy video or .npz mesh sequence, for --preview")

    r = sub.add_parser("rd", help="sweep QPs over mode sets, print JSON, write an RD plot")
    r.add_argument("--input", type=Path, help="uint16 (T, H, W, 3) .npy (default: ICT blendshape video)")
    r.add_argument("--frames", type=int, default=8, help="frames of the default ICT video (default 8)")
    r.add_argument("--size", type=int, default=256, help="image side of the default ICT video (default 256)")
    r.add_argument("--qps", default="18,30,42,54", help="comma list of quantisers (default 18,30,42,54)")
    r.add_argument("--configs", default="hip-intra,hip+pdp-intra,hip+pdp+pvm",
                   help="comma list from facesynth.codec.rd.CONFIGS")
    r.add_argument("--block-sizes", default=None, help="comma list from 4, 8, 16 (default: 8,16 with "
                   "the 8x8 transform, else 4,8,16)")
    r.add_argument("--no-transform8", action="store_true", help="4x4 transform for every block size")
    r.add_argument("--plot", type=Path, default=Path("codec_rd.png"), help="RD plot PNG (default codec_rd.png)")
    r.add_argument("--save-json", type=Path, metavar="FILE", help="also write the figures here (JSON)")


def _codec_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--modes", choices=["hip", "hip+pdp", "hip+pdp-spatial"], default="hip+pdp",
                   help="intra prediction: HIP only, HIP + PDP (default) or HIP + spatial-only PDP")
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


def _read_npy(path: Path, field: str) -> np.ndarray:
    """The array in ``path``; FacesynthError naming ``field`` when missing or unreadable."""
    if not path.is_file():
        raise FacesynthError(f"{field}: file not found")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error here
        raise FacesynthError(f"{field}: not a readable .npy file ({str(exc)[:120]})") from None


def _load_video(path: Path) -> np.ndarray:
    v = _read_npy(path, str(path))
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
    m = _read_npy(path, f"--mask {path}")
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


def _refuse_overwriting_inputs(args: argparse.Namespace) -> None:
    """FacesynthError when an output path of the action is one of its inputs."""
    from facesynth.io import refuse_overwriting_inputs

    a = vars(args)
    out, inp = a.get("output"), a.get("input")
    outputs = [out, a.get("preview"), a.get("plot"), a.get("save_json")]
    if out is not None and args.action in ("geometry", "scan"):
        outputs += [out.with_suffix(".mask.npy"), out.with_suffix(".scan.npz")]
    if out is not None and args.action == "encode":
        outputs.append(Path(str(out) + ".layout.npz"))
    inputs = [inp, a.get("mask"), a.get("layout"), a.get("reference"), a.get("landmarks"), *(a.get("inputs") or [])]
    if inp is not None and args.action in ("encode", "rd"):
        inputs.append(inp.with_suffix(".mask.npy"))
    if inp is not None and args.action == "decode":
        inputs.append(Path(str(inp) + ".layout.npz"))
    refuse_overwriting_inputs(outputs, inputs)


def run(args: argparse.Namespace) -> int:
    from facesynth.io import check_writable

    _refuse_overwriting_inputs(args)  # before any work, for every action
    if args.action == "scan":
        from facesynth.codec import scan_cli

        return scan_cli.run(args)
    if args.action in ("geometry", "encode", "decode"):
        check_writable(args.output)  # before the work
    action = {"geometry": _geometry, "encode": _encode, "decode": _decode, "rd": _rd}[args.action]
    figures = action(args)
    progress.result(_line(args.action, figures), figures)
    return 0


def _line(action: str, figures: dict) -> str:
    """A codec action's result for a person: what it wrote and its main figures."""
    wrote = [figures[k] for k in ("output", "plot") if figures.get(k)]
    shown = {"shape": "shape {}", "bytes": "{} bytes", "bits_per_frame": "{:.0f} bits/frame", "psnr_db": "PSNR {:.2f} dB",
             "decode_fps": "{:.1f} frames/s", "encode_fps": "{:.1f} frames/s"}
    parts = [fmt.format(figures[k]) for k, fmt in shown.items() if figures.get(k) is not None]
    return f"codec {action}: wrote {', '.join(map(str, wrote)) or 'nothing'}" + (f" ({', '.join(parts)})" if parts else "")


def _geometry(args: argparse.Namespace) -> dict:
    """The ICT face's geometry video (.npy) and its mask."""
    from facesynth.io import save_npy

    vid, mask, q = _ict_video(args.frames, args.size, args.seed)
    save_npy(args.output, vid)
    save_npy(args.output.with_suffix(".mask.npy"), mask)
    return {"output": str(args.output), "shape": list(vid.shape), "mask_share": float(mask.mean()),
            "bbox_lo": q.lo.tolist(), "bbox_hi": q.hi.tolist(), "diag": q.diag}


def _encode(args: argparse.Namespace) -> dict:
    """A geometry video (.npy) or mesh sequence (.npz) -> one bitstream; its figures."""
    from facesynth import progress
    from facesynth.codec import meshvideo
    from facesynth.codec.bitstream import encode_video
    from facesynth.codec.frame import CodecConfig
    from facesynth.codec.rd import modes_config
    from facesynth.io import write_bytes
    from facesynth.metrics import psnr

    bbox, seq = None, None
    if meshvideo.is_mesh_sequence(args.input):
        seq = meshvideo.load_mesh_sequence(args.input)
        with progress.stage("geometry video") as st:
            video, mask, qz = meshvideo.mesh_to_video(seq, args.size)
            st.set(f"{len(video)} meshes -> {args.size}x{args.size} images")
        bbox = np.stack([qz.lo, qz.hi])
        mask = _load_mask(args.mask, args.input, video.shape[1:3]) if args.mask else mask
    else:
        video = _load_video(args.input)
        mask = _load_mask(args.mask, args.input, video.shape[1:3])
    if args.gop < 1:
        raise FacesynthError(f"--gop: expected >= 1, got {args.gop}")
    cfg = CodecConfig(qp=None if args.lossless else args.qp, block_sizes=_sizes(args.block_sizes),
                      mv_range=args.mv_range, transform8=not args.no_transform8,
                      **modes_config(args.modes, args.gop, not args.no_inter))
    with progress.stage("encode") as st:
        data, rec, st_ = encode_video(video, cfg, mask, bbox)
        st.set(f"{len(video)} frames, {len(data)} bytes")
    write_bytes(args.output, data)
    out = {"output": str(args.output)}
    if seq is not None:
        out["layout"] = str(meshvideo.write_layout(args.output, seq, args.size))
    st_["psnr_db"] = psnr(video, rec, mask, peak=65535)
    st_["psnr_db"] = None if not np.isfinite(st_["psnr_db"]) else st_["psnr_db"]
    st_["encode_fps"] = len(video) / st_.pop("encode_s")
    if args.preview:
        from facesynth.codec.preview import write_preview

        out["preview"] = {"path": str(args.preview), **write_preview(video, rec, mask, args.preview,
                                                                       title=f"{args.input.name}, {args.modes}")}
    return {**out, **st_}


def _decode(args: argparse.Namespace) -> dict:
    """A bitstream -> the video (.npy) or the meshes (.npz); its figures."""
    from facesynth import progress
    from facesynth.codec.bitstream import decode_video
    from facesynth.io import atomic_path, save_npy

    if not args.input.is_file():
        raise FacesynthError(f"{args.input}: file not found")
    if args.preview and args.reference is None:
        raise FacesynthError("--preview needs --reference (the original .npy video or .npz mesh sequence)")
    with progress.stage("decode"):
        frames, info, st = decode_video(args.input.read_bytes())
    out = {"output": str(args.output), "shape": list(frames.shape), "qp": info.qp,
           "decode_fps": len(frames) / max(st["decode_s"], 1e-9)}
    if args.mesh:
        from facesynth.codec import meshvideo

        lay = meshvideo.read_layout(args.layout or Path(str(args.input) + meshvideo.LAYOUT_SUFFIX))
        with progress.stage("mesh from geometry video"):
            verts = meshvideo.video_to_mesh(frames, lay, info.bbox)
        with atomic_path(args.output) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, vertices=verts.astype(np.float32), faces=lay["faces"].astype(np.int32),
                     uvs=lay["uvs"].astype(np.float32))
        out["vertices_shape"] = list(verts.shape)
    else:
        save_npy(args.output, frames)
    if args.preview:
        out["preview"] = _decode_preview(args, frames, info)
    return out


def _decode_preview(args: argparse.Namespace, frames: np.ndarray, info) -> dict:
    """The preview of decoded ``frames`` against ``--reference`` (a video or a mesh sequence)."""
    from facesynth.codec import meshvideo
    from facesynth.codec.geometry import Quantiser, build_layout, geometry_video
    from facesynth.codec.preview import write_preview

    if meshvideo.is_mesh_sequence(args.reference):
        ref_seq = meshvideo.load_mesh_sequence(args.reference)
        if info.bbox is None or not np.isfinite(info.bbox).all():
            raise FacesynthError(f"{args.input}: the stream has no quantiser box to rasterise --reference with")
        lay = build_layout(ref_seq["faces"], ref_seq["uvs"], (info.height, info.width))
        ref, _ = geometry_video(lay, ref_seq["vertices"], Quantiser(info.bbox[0], info.bbox[1]))
        mask = lay.mask
    else:
        ref, mask = _load_video(args.reference), None
    if ref.shape != frames.shape:
        raise FacesynthError(f"--reference {args.reference}: shape {ref.shape} differs from the decoded {frames.shape}")
    return {"path": str(args.preview), **write_preview(ref, frames, mask, args.preview)}


def _rd(args: argparse.Namespace) -> dict:
    """Rate-distortion sweep of the configurations over the QPs, with a plot (and --json)."""
    from facesynth.codec.frame import CodecConfig
    from facesynth.codec.rd import CONFIGS, bd_between, plot_rd, rd_sweep
    from facesynth.io import write_json

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
    if args.save_json:
        write_json(args.save_json, result)
    return result
