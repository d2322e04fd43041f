"""``facesynth transfer3d``: drive a 3D face mesh with the head pose and expressions of
landmarks (and optionally render a preview video and a contact sheet)."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from facesynth import progress
from facesynth.errors import FacesynthError

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh", required=True, help="neutral face mesh (OBJ/PLY/...; read with trimesh, vertex order kept)")
    p.add_argument("--landmark-map", required=True, help="JSON {'map': {'1'..'68': vertex}} (1-based iBUG -> 0-based vertex)")
    p.add_argument("--landmarks", required=True, help="landmarks: a clip folder (landmarks.npy [+ video.mp4]), .npy, .npz or .pts folder")
    p.add_argument("--out", required=True, help="output .npz: vertices (T,V,3), faces, uvs, R, t, K, frame_index, ...")
    p.add_argument("--method", choices=("plain", "iterative", "dual"), default="plain",
                   help="Laplacian deformation: plain cotangent solve, iterative (Au et al.) or dual Laplacian")
    p.add_argument("--constraints", choices=("hard", "soft"), default="hard", help="handle constraints")
    p.add_argument("--weight", type=float, default=1.0, help="soft-constraint weight")
    p.add_argument("--anchors", choices=("rim", "none"), default="rim",
                   help="also fix the mesh's outer boundary loop (back of head, neck) at rest (default), or landmarks only")
    p.add_argument("--pose-method", default="epnp", choices=("dlt", "ndlt", "epnp", "cv-epnp", "cv-sqpnp", "cv-iterative"),
                   help="head-pose solver: direct linear transform (dlt), normalised DLT (ndlt), our EPnP (default), "
                        "or OpenCV's EPnP / SQPnP / iterative solvePnP")
    p.add_argument("--movement", choices=("transformation", "projection"), default="transformation",
                   help="movement vectors: similarity-aligned neutral frame (default) or residual to the projected model")
    p.add_argument("--image-size", default=None, metavar="WxH",
                   help="frame size of the landmarks' video (default: from the frames or meta.json)")
    p.add_argument("--fov", type=float, default=40.0, help="assumed horizontal field of view of the video camera, degrees")
    p.add_argument("--neutral-frame", type=int, default=None, help="row of the neutral reference frame (default: automatic as for ERI: the "
                        "closed-mouth frame closest to the mean shape, facesynth.neutral.select_neutral)")
    p.add_argument("--smooth", action="store_true", help="One Euro smoothing of the pose over time (off by default)")
    p.add_argument("--smooth-min-cutoff", type=float, default=1.0, help="One Euro min cutoff, Hz")
    p.add_argument("--smooth-beta", type=float, default=0.5, help="One Euro speed coefficient (rotation, per rad/s)")
    p.add_argument("--max-frames", type=int, default=None, help="process at most this many frames")
    p.add_argument("--stride", type=int, default=1, help="process every STRIDE-th frame")
    p.add_argument("--tol", type=float, default=1e-3, help="relative-change threshold of the iterative methods")
    p.add_argument("--max-iter", type=int, default=30, help="iteration cap of the iterative methods")
    p.add_argument("--render", default=None, help="write a shaded preview video (.mp4): video | posed mesh | frontal")
    p.add_argument("--video", default=None,
                   help="source video for the preview (default: the landmark source's video / frames, if any)")
    p.add_argument("--contact-sheet", default=None, help="write a PNG of characteristic frames (jaw, lips, brows)")


def _frames_and_fps(args) -> tuple:
    """The frame source for the preview (``--video``, ``video.mp4`` beside a ``.npy``, or
    whatever the landmark source carries: an ingest folder's video, an .npz's frames) and
    the frame rate (30 when unknown)."""
    from facesynth.data import load_sequence
    from facesynth.data.frames import VideoFrames

    lp = Path(args.landmarks)
    video = Path(args.video) if args.video else None
    if video is None and lp.is_file() and (lp.with_name("video.mp4")).is_file():
        video = lp.with_name("video.mp4")
    if video is not None:
        vf = VideoFrames(video)
        return vf, vf.fps or 30.0
    try:
        seq = load_sequence(lp, scheme="ibug68")
    except FacesynthError:
        return None, 30.0
    return seq.frames, float(seq.fps or 30.0)


def _image_size(args, frames, lm) -> tuple[int, int]:
    if args.image_size:
        try:
            w, h = (int(v) for v in args.image_size.lower().split("x"))
            assert w > 0 and h > 0
        except (ValueError, AssertionError):
            raise FacesynthError(f"--image-size {args.image_size!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
        return w, h
    if frames is not None:
        h, w = frames.size
        return w, h
    meta = Path(args.landmarks) / "meta.json"
    if meta.is_file():
        v = json.loads(meta.read_text()).get("video", {})
        if v.get("width") and v.get("height"):
            return int(v["width"]), int(v["height"])
    finite = lm[np.isfinite(lm).all(axis=(1, 2))]
    log.warning("frame size unknown: guessed from the landmarks' extent (give --image-size for a correct camera)")
    return int(np.ceil(finite[..., 0].max() * 1.2)), int(np.ceil(finite[..., 1].max() * 1.2))


def _rows_and_neutral(args, lm: np.ndarray) -> tuple[np.ndarray, list[int], int, str]:
    """The rows to transfer (--stride, --max-frames, finite landmarks only), the skipped rows
    with NaN landmarks, and the neutral frame with the rule that chose it."""
    from facesynth.neutral import select_neutral

    rows = np.arange(0, len(lm), args.stride)
    if args.max_frames is not None:
        rows = rows[: args.max_frames]
    finite = np.isfinite(lm).all(axis=(1, 2))
    skipped = [int(r) for r in rows if not finite[r]]
    rows = np.array([r for r in rows if finite[r]], np.int64)
    if skipped:
        log.warning("%d frames with NaN landmarks skipped (first: %d)", len(skipped), skipped[0])
    if len(rows) == 0:
        raise FacesynthError(f"{args.landmarks}: no frame with finite landmarks to transfer")
    if args.neutral_frame is None:
        cand = np.flatnonzero(finite)
        pick, info = select_neutral(lm[cand])
        neutral, neutral_rule = int(cand[pick]), f"automatic ({info['rule']}, closest to the mean shape)"
    else:
        neutral, neutral_rule = args.neutral_frame, "--neutral-frame"
    if not 0 <= neutral < len(lm) or not finite[neutral]:
        raise FacesynthError(f"--neutral-frame {neutral}: not a frame with finite landmarks (0..{len(lm) - 1})")
    progress.note(f"neutral frame: {neutral} ({neutral_rule})")
    return rows, skipped, neutral, neutral_rule


def _transfer_rows(args, tr, mesh, lmap, lm: np.ndarray, rows: np.ndarray, neutral: int, frames, fps: float,
                   size: tuple[int, int]) -> tuple[dict, float]:
    """Transfer every row (rendering the preview video and the contact sheet on the way);
    the per-frame arrays of the output file and the seconds spent in the solves."""
    from facesynth.mesh.preview import PreviewWriter, contact_sheet, panel, pick_sheet_frames

    T, n = len(rows), len(mesh.vertices)
    verts = np.empty((T, n, 3), np.float32)
    Rs, ts, Ks = np.empty((T, 3, 3)), np.empty((T, 3)), np.empty((T, 3, 3))
    iters, conv, reproj = np.empty(T, np.int32), np.empty(T, bool), np.empty(T)
    sheet = dict(pick_sheet_frames(lm[rows], int(np.argmin(np.abs(rows - neutral)))))  # the processed row nearest the neutral
    sheet_rows, sheet_labels = {}, {}
    writer = PreviewWriter(args.render, fps / args.stride) if args.render else None
    frame_iter = frames.read(rows) if frames is not None else None
    t_solve = 0.0
    ok = False
    what = "transfer + render" if writer is not None else "transfer"
    bar = progress.bar(total=T, desc=what, unit="frame")
    t_loop = time.perf_counter()
    try:
        for k, r in enumerate(rows):
            t1 = time.perf_counter()
            res = tr.frame(lm[r], t_s=r / fps)
            t_solve += time.perf_counter() - t1
            verts[k], Rs[k], ts[k], Ks[k] = res.vertices, res.pose.R, res.pose.t, res.pose.K
            iters[k], conv[k] = res.info.iterations, res.info.converged
            reproj[k] = res.pose.reprojection_error(mesh.vertices[lmap[tr.pose_idx]], lm[r][tr.pose_idx])
            img = next(frame_iter) if frame_iter is not None else None
            if writer is not None or k in sheet:
                row = panel(img, res.vertices, mesh.faces, res.pose.R, res.pose.t, res.pose.K, size, mesh.vertices, lm[r])
                if writer is not None:
                    writer.write(row)
                if k in sheet:
                    sheet_rows[k], sheet_labels[k] = row, f"#{int(r)} {sheet[k]}"
            bar.update(1)
        ok = True
    finally:
        bar.close()
        if writer is not None:
            writer.close(ok)
    progress.note(f"{what}: {T} frames in {time.perf_counter() - t_loop:.1f} s")
    if args.contact_sheet:
        keys = [k for k in sheet if k in sheet_rows]
        contact_sheet([sheet_rows[k] for k in keys], [sheet_labels[k] for k in keys], args.contact_sheet)
    return {"vertices": verts, "R": Rs, "t": ts, "K": Ks, "iterations": iters, "converged": conv,
            "pose_reprojection_px": reproj}, t_solve


def run(args: argparse.Namespace) -> int:
    from facesynth.data import load_landmarks
    from facesynth.io import atomic_path
    from facesynth.mesh.io import load_landmark_map, load_mesh
    from facesynth.mesh.smoothing import PoseFilter
    from facesynth.mesh.transfer import Transfer, TransferConfig
    from facesynth.provenance import array_fingerprint, file_sha256, package_versions

    if not str(args.out).endswith(".npz"):
        raise FacesynthError(f"--out {args.out}: the mesh sequence is written as .npz")
    if args.stride < 1:
        raise FacesynthError("--stride must be >= 1")
    mesh = load_mesh(args.mesh)
    lmap = load_landmark_map(args.landmark_map, len(mesh.vertices))
    lm = load_landmarks(args.landmarks, scheme="ibug68")
    rows, skipped, neutral, neutral_rule = _rows_and_neutral(args, lm)

    frames, fps = _frames_and_fps(args)
    size = _image_size(args, frames, lm)
    if not (args.render or args.contact_sheet):
        frames = None
    cfg = TransferConfig(method=args.method, constraints=args.constraints, weight=args.weight, pose_method=args.pose_method,
                         fov_deg=args.fov, movement=args.movement, tol=args.tol, max_iter=args.max_iter,
                         anchors=args.anchors)
    pf = PoseFilter(args.smooth_min_cutoff, beta_r=args.smooth_beta) if args.smooth else None
    t0 = time.perf_counter()
    tr = Transfer(mesh, lmap, size, cfg, pose_filter=pf)
    t_factor = time.perf_counter() - t0
    tr.set_reference(lm[neutral])
    out, t_solve = _transfer_rows(args, tr, mesh, lmap, lm, rows, neutral, frames, fps, size)

    T = len(rows)
    summary = {
        "frames": T, "skipped_nan_frames": len(skipped), "neutral_frame": neutral, "neutral_rule": neutral_rule, "method": args.method,
        "factorisation_s": round(t_factor, 4), "ms_per_frame_transfer": round(1e3 * t_solve / T, 3),
        "iterations_mean": float(out["iterations"].mean()), "converged_fraction": float(out["converged"].mean()),
        "pose_reprojection_px_mean": float(out["pose_reprojection_px"].mean()),
    }
    meta = {
        "config": {k: v for k, v in vars(args).items() if k != "func"}, "summary": summary,
        "mesh_sha256": file_sha256(args.mesh), "landmarks_fingerprint": array_fingerprint(np.nan_to_num(lm)),
        "packages": package_versions(),
        "conventions": "vertices in the mesh frame (y up, +z to viewer); camera X_c = R X + t (y down, z forward); pixels = K X_c",
    }
    with atomic_path(args.out) as tmp, open(tmp, "wb") as f:
        np.savez(
            f, vertices=out["vertices"], faces=mesh.faces.astype(np.int32),
            uvs=mesh.uvs if mesh.uvs is not None else np.zeros((0, 2), np.float32),
            R=out["R"], t=out["t"], K=out["K"], frame_index=rows, handles=tr.handles, iterations=out["iterations"],
            converged=out["converged"], pose_reprojection_px=out["pose_reprojection_px"],
            skipped_frames=np.array(skipped, np.int64), meta=json.dumps(meta, default=str),
        )
    progress.result(f"transferred {T} frames -> {args.out} ({args.method}, {summary['ms_per_frame_transfer']:.1f} "
                    f"ms/frame, pose reprojection {summary['pose_reprojection_px_mean']:.2f} px)", summary)
    return 0
