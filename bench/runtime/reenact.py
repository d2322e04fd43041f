"""Reenactment figures (issue 13): avatars driven by other people, one JSON line.

    OMP_NUM_THREADS=1 python -m bench.runtime.reenact [--work /tmp/facesynth_reenact] [--sheets docs]
        [--dense /tmp/dense]

``--dense DIR``: 478-point avatars and drivers instead, from ``DIR/CLIP`` folders that
``facesynth ingest --landmarker mediapipe`` wrote (the pairs whose two clips are there; the
figures measured on the landmarks' iBUG-68 view).

Each avatar is a linear model trained on its clip with ``train.py data=video regressor=linear``
(its training split) and exported with ``facesynth export`` (trained once into ``--work``).
Per pair (avatar <- driver, relative motion, driver neutral by ERI's rule): hull coverage
(min / median over frames, frames below 99 %), Pearson r of mouth and eye opening, the
jaw-width / nose-bridge-to-chin ratio against the avatar's own training frames
(:mod:`facesynth.eval.reenact`). Self-driving: each avatar's held-out frames, relative
vs absolute motion, frame-level PSNR (the driver's neutral is then the
avatar's own neutral frame). Speed: model call and retargeting CPU time per frame
(batch 1, one thread, same run). ``--sheets DIR`` writes a contact sheet per pair
(driver above, avatar output below) as ``reenact_AVATAR_by_DRIVER.jpg``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]

from bench.harness import emit, load_average  # noqa: E402
from facesynth.data import load_sequence, shared_clip  # noqa: E402
from facesynth.eval.reenact import pair_figures, self_driving_psnr, speed  # noqa: E402
from facesynth.rundir import read_config, run_data  # noqa: E402
from facesynth.runtime.renderer import read_metadata  # noqa: E402

PAIRS = (("lp_d3", "lp_d6"), ("lp_d10", "lp_d13"), ("lp_d20", "lp_d6"))  # lp_d20: a three-quarter view
SHEET_COLUMNS = 6


def model_for(clip: str, work: Path, dense: Path | None = None, regressor: str = "linear") -> tuple[Path, Path]:
    """(run directory, exported ONNX) of an avatar model of ``clip`` (the shared clip, or
    ``dense / clip``) with ``regressor`` (every other setting the default), trained if missing."""
    tag = (clip if dense is None else f"{clip}_mp478") + ("" if regressor == "linear" else f"_{regressor}")
    run, onnx_path = work / f"run_{tag}", work / f"{tag}.onnx"
    if not onnx_path.is_file():
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        subprocess.run([sys.executable, str(ROOT / "train.py"), "data=video", f"data.path={clip_dir(clip, dense)}",
                        f"regressor={regressor}", "eval.frame_level=false", f"hydra.run.dir={run}"], check=True, cwd=ROOT, env=env,
                       stdout=subprocess.DEVNULL)
        subprocess.run([sys.executable, "-m", "facesynth", "export", str(run), "--out", str(onnx_path)], check=True, cwd=ROOT,
                       env=env, stdout=subprocess.DEVNULL)
    return run, onnx_path


def clip_dir(clip: str, dense: Path | None) -> Path:
    return shared_clip(clip) if dense is None else dense / clip


def sheet(driver_frames: list, avatar_frames: list, width: int = 180) -> np.ndarray:
    def thumb(img):
        h, w = img.shape[:2]
        return cv2.resize(img, (width, int(round(h * width / w))), interpolation=cv2.INTER_AREA)

    rows = [np.concatenate([thumb(i) for i in r], 1) for r in (driver_frames, avatar_frames)]
    w = min(r.shape[1] for r in rows)
    return np.concatenate([r[:, :w] for r in rows], 0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/facesynth_reenact", help="where models are trained and exported")
    ap.add_argument("--sheets", help="directory for the contact sheets (JPEG)")
    ap.add_argument("--reps", type=int, default=500, help="timed frames for the speed figures")
    ap.add_argument("--dense", type=Path, help="folders of 478-point ingests (DIR/CLIP): reenact those instead")
    args = ap.parse_args()
    dense = args.dense
    pairs = [p for p in PAIRS if dense is None or all((dense / c / "landmarks.npy").is_file() for c in p)]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    out = {"load_average_start": load_average(), "scheme": "ibug68" if dense is None else "mediapipe478", "pairs": {}}
    for avatar, driver in pairs:
        run, path = model_for(avatar, work, dense)
        seq, rows, _ = run_data(read_config(run))
        drv = load_sequence(clip_dir(driver, dense))
        lm = np.asarray(drv.landmarks, np.float32)
        picks = set(np.linspace(0, len(lm) - 1, SHEET_COLUMNS).round().astype(int).tolist())
        res = pair_figures(path, lm, seq.landmarks[rows], sheet_rows=picks)
        out["pairs"][f"{avatar}<-{driver}"] = res["figures"]
        if args.sheets:
            rows_shown = sorted(picks)
            img = sheet([drv.frame(i) for i in rows_shown], [res["frames"][i] for i in rows_shown])
            dest = Path(args.sheets) / f"reenact_{avatar}_by_{driver}{'' if dense is None else '_mp478'}.jpg"
            cv2.imwrite(str(dest), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
    # self-driving on each avatar's held-out frames; the clip drives its own avatar, so its
    # neutral is the avatar's (app: --driver-neutral AVATAR_NEUTRAL_ROW)
    out["self_driving"] = {}
    for avatar in dict.fromkeys(a for a, _ in pairs):
        run, path = model_for(avatar, work, dense)
        seq, _, test = run_data(read_config(run))
        held = np.asarray(seq.landmarks[test], np.float32)
        neutral = np.asarray(read_metadata(path)["avatar_neutral"], np.float32)
        out["self_driving"][avatar] = self_driving_psnr(path, held, seq.iter_frames(test), neutral)
    avatar = pairs[0][0]
    run, path = model_for(avatar, work, dense)
    lm = np.asarray(load_sequence(clip_dir(pairs[0][1], dense)).landmarks, np.float32)
    out["speed"] = {"model": f"{avatar}.onnx", **speed(path, lm, reps=args.reps)}
    out["load_average_end"] = load_average()
    out["wall_s"] = round(time.time() - t0, 1)
    emit(out)
if __name__ == "__main__":
    main()
