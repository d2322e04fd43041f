"""``facesynth transfer-expression``: render a target face performing a driver's expressions
with a trained ERI model (FAPs of the driver -> ratio images + geometry on the target)."""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from facesynth import progress
from facesynth.errors import FacesynthError

log = logging.getLogger(__name__)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--eri", required=True, metavar="RUN", help="training run folder (or its eri/ model folder)")
    p.add_argument("--target", required=True, metavar="IMAGE_OR_DIR",
                   help="target neutral face: an image, or a folder in ingest layout (its neutral frame is used)")
    p.add_argument("--target-landmarks", metavar="L", help="landmarks of the target image (.npy (68, 2)/(N, 68, 2) or .pts)")
    p.add_argument("--target-frame", type=int, metavar="ROW",
                   help="row of the target folder (or of --target-landmarks) to use as neutral (default: automatic)")
    p.add_argument("--driver", required=True, metavar="DIR", help="driver sequence (ingest folder or landmark file)")
    p.add_argument("--driver-neutral", type=int, metavar="ROW",
                   help="driver's neutral row (default: the model's neutral when the driver is its training clip, else automatic)")
    p.add_argument("--out", required=True, metavar="OUT.mp4", help="output video (written atomically)")
    p.add_argument("--sheet", metavar="OUT.png", help="contact sheet: driver frame | geometry-only warp | ERI result")
    p.add_argument("--sheet-rows", type=int, default=6, help="frames on the contact sheet (default 6)")
    p.add_argument("--variant", choices=["eps_linear", "eps_rbf", "nu_linear", "nu_rbf"], help="SVR variant (default: the model's)")
    p.add_argument("--raw-ratios", action="store_true",
                   help="apply the predicted ratios as they are (no edge confidence / brightening cap)")
    p.add_argument("--max-frames", type=int, default=0, help="render only the first N driver frames (0 = all)")
    p.add_argument("--fps", type=float, help="output frame rate (default: the driver's)")
    p.add_argument("--still-frame", action="store_true",
                   help="composite into the target image as it is (default: the image warped with the face, so that "
                        "its jaw, neck and hair follow the expression; facesynth.runtime.fullframe)")


def run(args) -> int:
    from facesynth.data import load_sequence
    from facesynth.eri.faps import compute_faps
    from facesynth.eri.geometry import select_neutral
    from facesynth.eri.model import EriModel
    from facesynth.eri.render import contact_sheet, pick_sheet_rows, write_video
    from facesynth.eri.synthesis import EriSynthesizer
    from facesynth.eri.target import load_target
    from facesynth.retarget import Retargeter
    from facesynth.runtime.fullframe import FrameWarp

    model = EriModel.load(args.eri)
    image, landmarks, target_desc = load_target(args.target, args.target_landmarks, args.target_frame)
    driver = load_sequence(args.driver, scheme="ibug68")
    if args.driver_neutral is not None:
        if not 0 <= args.driver_neutral < len(driver):
            raise FacesynthError(f"--driver-neutral {args.driver_neutral} is outside {args.driver} (0..{len(driver) - 1})")
        d_neutral, how = driver.landmarks[args.driver_neutral], f"row {args.driver_neutral}"
    elif driver.fingerprint == model.fingerprint:
        d_neutral, how = model.neutral_landmarks, f"the model's neutral (row {model.neutral_index})"
    else:
        row = select_neutral(driver.landmarks, model.config.mouth_closed_max)[0]
        d_neutral, how = driver.landmarks[row], f"row {row} (automatic)"
    n = len(driver) if args.max_frames <= 0 else min(args.max_frames, len(driver))
    faps = compute_faps(driver.landmarks[:n], d_neutral)
    syn = EriSynthesizer(model, image, landmarks, args.variant, raw=args.raw_ratios)
    # B's landmarks: the driver's expression retargeted onto B's face (FAP units extended to
    # every point, B's own proportions; the app's retargeting), in B's head pose
    positions = Retargeter(syn.neutral, d_neutral, head_motion=False)(driver.landmarks[:n])
    t0 = time.perf_counter()

    # B's image warped with the face (jaw, neck and hair follow the expression), or as it is
    background = None if args.still_frame else FrameWarp(image, syn.neutral)
    rendered = progress.bar(syn.iter_render(faps, "eri", positions=positions, background=background), total=n,
                            desc="render", unit="frame")
    with progress.stage("transfer-expression render") as st:
        frames = write_video(args.out, rendered, args.fps or driver.fps)
        st.set(f"{frames} frames")
    per_frame = (time.perf_counter() - t0) / frames
    summary = {"out": str(args.out), "frames": frames, "seconds_per_frame": per_frame, "target": target_desc,
               "driver": str(args.driver), "driver_neutral": how, "variant": syn.variant,
               "frame_warp": background is not None}
    if args.sheet:
        if not driver.has_frames:
            raise FacesynthError(f"{args.driver}: the contact sheet needs the driver's frames (video)")
        rows = pick_sheet_rows(faps, args.sheet_rows)
        bgs = None if background is None else np.stack([background(p) for p in positions[rows]])
        geo, _ = syn.render(faps[rows], "geometry", backgrounds=bgs, positions=positions[rows])
        eri, _ = syn.render(faps[rows], "eri", backgrounds=bgs, positions=positions[rows])
        contact_sheet(args.sheet, list(driver.iter_frames(rows)), driver.landmarks[rows], list(geo), list(eri),
                      positions[rows])
        summary.update(sheet=str(args.sheet), sheet_rows=rows.tolist())
    progress.result(f"{frames} frames -> {args.out} ({per_frame * 1e3:.0f} ms/frame, variant {syn.variant})"
                    + (f", sheet -> {args.sheet}" if args.sheet else ""), summary)
    return 0
