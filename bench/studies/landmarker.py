"""The default-landmarker decision table of docs/landmarks.md: dlib (``ibug68``) against MediaPipe
(``mediapipe478``) on every shared clip, from run folders that were already trained.

Per clip: each landmarker's detection rate and ingest speed (``meta.json`` of its ingest folder;
dlib's shipped detection rate from the clip's own ``meta.json``), held-out frame-level
``psnr_frame_common`` at sigma 0 of the SADM row, whole and per part, and the whole face's
``sharpness_frame_common`` (``metrics.json`` of each scheme's default ``facesynth train`` run).

Folders under ROOT (default /tmp/lm_study), one per clip::

    dlib_data/CLIP   facesynth ingest $D/CLIP/video.mp4 --out ...                          (timing only)
    mp_data/CLIP     facesynth ingest $D/CLIP/video.mp4 --out ... --landmarker mediapipe
    ib/CLIP          facesynth train data=video data.path=$D/CLIP hydra.run.dir=...        (ibug68)
    mp/CLIP          facesynth train data=video data.path=ROOT/mp_data/CLIP hydra.run.dir=...
    logs/            each command's output (the error of a run that failed is read from it)

    python -m bench.studies.landmarker [--root DIR] [--clips lp_d6 ...] [--train]

Prints ONE JSON line (per clip and a summary), then the markdown tables. Trains nothing unless
``--train`` is given: then it first runs the missing ingests and trainings above, one at a time.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from facesynth.data.shared import shared_data_dir

PARTS = ("eyes", "mouth_interior", "lips", "brows", "rest")
SCHEMES = {"ib": "ibug68", "mp": "mediapipe478"}


def _commands(root: Path, faces: Path, clip: str) -> list[tuple[Path, str, list[str]]]:
    """(output that marks it done, log name, argv) of one clip's four steps, in order."""
    video = str(faces / clip / "video.mp4")
    train = [sys.executable, "-m", "facesynth", "train", "data=video"]
    return [
        (root / "dlib_data" / clip / "meta.json", f"dlib_ingest_{clip}",
         [sys.executable, "-m", "facesynth", "ingest", video, "--out", str(root / "dlib_data" / clip), "--no-progress"]),
        (root / "mp_data" / clip / "meta.json", f"mp_ingest_{clip}",
         [sys.executable, "-m", "facesynth", "ingest", video, "--out", str(root / "mp_data" / clip), "--landmarker", "mediapipe",
          "--no-progress"]),
        (root / "ib" / clip / "metrics.json", f"ib_{clip}",
         train + [f"data.path={faces / clip}", f"hydra.run.dir={root / 'ib' / clip}"]),
        (root / "mp" / clip / "metrics.json", f"mp_{clip}",
         train + [f"data.path={root / 'mp_data' / clip}", f"hydra.run.dir={root / 'mp' / clip}"]),
    ]


def train_missing(root: Path, faces: Path, clips: list[str]) -> None:
    (root / "logs").mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for clip in clips:
        for done, log, argv in _commands(root, faces, clip):
            if not done.is_file():
                with open(root / "logs" / f"{log}.log", "w") as out:
                    t0 = time.perf_counter()
                    subprocess.run(argv, stdout=out, stderr=subprocess.STDOUT, env=env, check=False)
                    out.write(f"wall {time.perf_counter() - t0:.2f} s\n")  # the line /usr/bin/time -f "wall %e s" writes


def _json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _failure(log: Path) -> str:
    """The last line of a failed run's log that names an error (or 'not run')."""
    if not log.is_file():
        return "not run"
    lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower()]
    return (errors or lines or ["empty log"])[-1][:300]


def _wall(log: Path) -> float | None:
    """A run's wall time from the 'wall S s' line of its log, if any."""
    found = re.findall(r"^wall ([0-9.]+) s", log.read_text(errors="replace"), re.M) if log.is_file() else []
    return float(found[-1]) if found else None


def _ingest(meta: dict | None) -> dict | None:
    if meta is None:
        return None
    st = meta["stats"]
    return {"frames": st.get("frames_processed"), "detection_rate": st["detection_rate"],
            "frames_per_s": st.get("frames_per_s"), "wall_s": st.get("wall_s")}


def _run(metrics: dict) -> dict:
    regions = metrics["psnr_frame_common_regions"]
    sharp = metrics["sharpness_frame_common"]
    # a part no evaluated frame shows (a mouth that stays closed has no interior) is absent: None
    psnr = {part: regions[part]["sadm"]["0"] if part in regions else None for part in ("whole",) + PARTS}
    below = [p for p in PARTS if p in regions and regions[p]["sadm"]["0"] < regions[p]["mean_texture"]["0"]]
    return {"psnr": psnr, "sharpness": sharp["whole"]["sadm"], "sharpness_eyes": sharp["eyes"]["sadm"],
            "parts_below_mean": below, "test_frames": metrics.get("frame_level_frames")}


def collect(root: Path, faces: Path, clip: str) -> dict:
    row = {"clip": clip, "dlib_shipped_detection_rate": _json(faces / clip / "meta.json")["stats"]["detection_rate"],
           "ingest": {"dlib": _ingest(_json(root / "dlib_data" / clip / "meta.json")),
                      "mediapipe": _ingest(_json(root / "mp_data" / clip / "meta.json"))}}
    for key in SCHEMES:
        metrics = _json(root / key / clip / "metrics.json")
        log = root / "logs" / f"{key}_{clip}.log"
        row[key] = {**_run(metrics), "train_wall_s": _wall(log)} if metrics else {"error": _failure(log)}
    if "psnr" in row["ib"] and "psnr" in row["mp"]:
        row["gain"] = {p: row["mp"]["psnr"][p] - row["ib"]["psnr"][p] for p in row["ib"]["psnr"]
                       if row["mp"]["psnr"][p] is not None and row["ib"]["psnr"][p] is not None}
    return row


def summarise(rows: list[dict]) -> dict:
    both = [r for r in rows if "gain" in r]
    out = {"clips": len(rows), "compared": len(both), "missing": [r["clip"] for r in rows if "gain" not in r]}
    for part in ("whole",) + PARTS:
        have = [r for r in both if part in r["gain"]]
        g = np.array([r["gain"][part] for r in have])
        if len(g):
            worst = have[int(np.argmin(g))]["clip"]
            out[part] = {"compared": len(g), "mp_wins": int((g > 0).sum()), "mean_gain_db": float(g.mean()),
                         "median_gain_db": float(np.median(g)),
                         "worst_db": float(g.min()), "worst_clip": worst, "best_db": float(g.max())}
    ds = np.array([r["mp"]["sharpness"] - r["ib"]["sharpness"] for r in both])
    if len(ds):
        out["sharpness_gain"] = {"mean": float(ds.mean()), "min": float(ds.min()), "max": float(ds.max()),
                                 "mp_higher": int((ds > 0.005).sum()), "mp_lower": int((ds < -0.005).sum())}
    for lm in ("dlib", "mediapipe"):
        ing = [r["ingest"][lm] for r in rows if r["ingest"][lm]]
        if ing:
            frames = sum(i["frames"] for i in ing)
            out[f"{lm}_ingest"] = {"clips": len(ing), "frames": frames, "detected_all": all(i["detection_rate"] == 1.0 for i in ing),
                                   "frames_per_s_overall": frames / sum(i["wall_s"] for i in ing)}
    for key in SCHEMES:
        out[f"{key}_parts_below_mean"] = {r["clip"]: r[key]["parts_below_mean"] for r in rows
                                          if r[key].get("parts_below_mean")}
    return out


def _f(x, fmt="{:.2f}") -> str:
    return "-" if x is None else fmt.format(x)


def markdown(rows: list[dict], summary: dict) -> str:
    main = ["| clip | frames | detection rate: MediaPipe / dlib (shipped) | ibug68 whole (dB) | mediapipe478 whole (dB) | gain |"
            " sharpness ibug68 / mediapipe478 | ingest frames/s: MediaPipe / dlib |",
            "|---|---|---|---|---|---|---|---|"]
    parts = ["| clip | " + " | ".join(p.replace("_", " ") for p in PARTS) + " |", "|---|" + "---|" * len(PARTS)]
    for r in rows:
        mp_i, dl_i = r["ingest"]["mediapipe"], r["ingest"]["dlib"]
        det = f"{_f(mp_i and mp_i['detection_rate'], '{:.3f}')} / {r['dlib_shipped_detection_rate']:.3f}"
        speed = f"{_f(mp_i and mp_i['frames_per_s'], '{:.0f}')} / {_f(dl_i and dl_i['frames_per_s'], '{:.0f}')}"
        ib, mp = r["ib"], r["mp"]
        if "gain" not in r:
            err = "; ".join(f"{SCHEMES[k]}: {r[k]['error']}" for k in SCHEMES if "error" in r[k])
            main.append(f"| {r['clip']} | {_f(mp_i and mp_i['frames'], '{}')} | {det} | not compared: {err} | | | | {speed} |")
            continue
        main.append(f"| {r['clip']} | {mp_i['frames']} | {det} | {ib['psnr']['whole']:.2f} | {mp['psnr']['whole']:.2f} | "
                    f"{r['gain']['whole']:+.2f} | {ib['sharpness']:.2f} / {mp['sharpness']:.2f} | {speed} |")
        parts.append(f"| {r['clip']} | " + " | ".join(
            f"{_f(ib['psnr'][p])} / {_f(mp['psnr'][p])}" + (f" ({r['gain'][p]:+.2f})" if p in r["gain"] else "")
            for p in PARTS) + " |")
    summ = ["| part | MediaPipe wins | mean gain | median | worst (clip) | best |", "|---|---|---|---|---|---|"]
    for p in ("whole",) + PARTS:
        if p in summary:
            s = summary[p]
            summ.append(f"| {p.replace('_', ' ')} | {s['mp_wins']} of {s['compared']} | {s['mean_gain_db']:+.2f} | "
                        f"{s['median_gain_db']:+.2f} | {s['worst_db']:+.2f} ({s['worst_clip']}) | {s['best_db']:+.2f} |")
    return "\n".join(main + [""] + parts + [""] + summ)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="/tmp/lm_study", help="folder of the ingests, runs and logs")
    ap.add_argument("--clips", nargs="*", help="default: every clip of shared/data/faces")
    ap.add_argument("--train", action="store_true", help="first ingest and train what is missing (slow)")
    args = ap.parse_args()
    data = shared_data_dir()
    if data is None:
        raise SystemExit("shared/data/faces not found (set FACESYNTH_SHARED_DATA)")
    faces, root = data / "faces", Path(args.root)
    clips = args.clips or sorted(p.name for p in faces.iterdir() if (p / "landmarks.npy").is_file())
    if args.train:
        train_missing(root, faces, clips)
    rows = [collect(root, faces, c) for c in clips]
    summary = summarise(rows)
    print(json.dumps({"clips": rows, "summary": summary}))
    print(markdown(rows, summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
