"""Contact sheet of test frames where the eyes look sideways: real | run A | run B (the eye
band of each frame, synthesized from the landmarks alone and pasted into the real frame).

    python -m bench.studies.gaze_sheet --data /tmp/gaze/lp_d6 --runs RUN_IBUG68 RUN_IRIS \\
        --labels ibug68 ibug68+iris --out docs/gaze_lp_d6.jpg [--n 6]

``--data`` is an ``ibug68+iris`` folder (its irises pick the frames: the test frames with the
largest |horizontal gaze|, half looking to each side, at least 10 frames apart); each run is
fed the landmarks of its own scheme (the first 68 points for an ``ibug68`` run), from
``--data`` or, for a run of another scheme (``mediapipe478``), from that run's entry of
``--landmarks`` (a folder ingested from the same video; ``-`` = ``--data``), matched by video
frame. Prints one JSON line (frames, gaze values, file size).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from facesynth.compositing import composite
from facesynth.data import load_sequence, temporal_split
from facesynth.io import atomic_path
from facesynth.landmarks import get_scheme
from facesynth.sadm.fit import load_sadm
from facesynth.sadm.gaze import gaze_features


def pick_frames(gx: np.ndarray, n: int, gap: int = 10) -> list[int]:
    """Positions of the ``n`` most sideways frames, half each side, ``gap`` apart."""
    chosen: list[int] = []
    for sign, k in ((-1, n // 2), (1, n - n // 2)):
        got = 0
        for i in np.argsort(sign * -gx):  # most extreme in this direction first
            if got == k:
                break
            if all(abs(int(i) - j) >= gap for j in chosen):
                chosen.append(int(i))
                got += 1
    return chosen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--labels", nargs="+", required=True)
    ap.add_argument("--landmarks", nargs="+", help="per run: a landmark folder of the same video, or - for --data")
    ap.add_argument("--out", required=True)
    ap.add_argument("--n", type=int, default=6)
    ap.add_argument("--width", type=int, default=300, help="width of each tile (px)")
    a = ap.parse_args()
    seq = load_sequence(a.data)
    _, te = temporal_split(len(seq), 0.75, 0)
    scheme = get_scheme(seq.scheme)
    g = gaze_features(scheme, seq.landmarks[te])
    gx = 0.5 * (g[:, 0] + g[:, 2])
    pos = pick_frames(gx, a.n)
    rows = te[pos]
    sadms = [load_sadm(r) for r in a.runs]
    sources = a.landmarks or ["-"] * len(a.runs)
    if len(sources) != len(a.runs) or len(a.labels) != len(a.runs):
        raise SystemExit("error: give one --labels entry (and one --landmarks entry, if any) per run")
    lms = []
    for src in sources:
        other = seq if src == "-" else load_sequence(src)
        where = {int(f): i for i, f in enumerate(other.frame_index)}
        lms.append(np.stack([other.landmarks[where[int(f)]] for f in seq.frame_index[rows]]))
    tiles = []
    for n_row, row in enumerate(rows):
        frame = seq.frame(int(row))
        lm = seq.landmarks[row]
        eye = lm[36:48]
        iod = float(np.linalg.norm(lm[45] - lm[36]))
        cx, cy = eye.mean(0)
        x0, x1 = int(cx - 0.95 * iod), int(cx + 0.95 * iod)
        y0, y1 = int(cy - 0.45 * iod), int(cy + 0.4 * iod)
        row_tiles = [frame]
        for sadm, run_lm in zip(sadms, lms, strict=True):
            p = get_scheme(sadm.scheme).n_points
            with torch.no_grad():
                crop, mask, place = sadm.synthesizer()(torch.from_numpy(run_lm[n_row][None, :p].copy()))
            row_tiles.append(composite(crop[0].permute(1, 2, 0).numpy(), mask[0, 0].numpy(), place[0].numpy(), frame))
        cut = [t[max(y0, 0):y1, max(x0, 0):x1] for t in row_tiles]
        h = int(round(a.width * cut[0].shape[0] / cut[0].shape[1]))
        tiles.append(np.concatenate([cv2.resize(c, (a.width, h), interpolation=cv2.INTER_AREA) for c in cut], 1))
    h = min(t.shape[0] for t in tiles)
    sheet = np.concatenate([t[:h] for t in tiles], 0)
    head = np.full((28, sheet.shape[1], 3), 255, np.uint8)
    for k, label in enumerate(["real"] + list(a.labels)):
        cv2.putText(head, label, (k * a.width + 8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    sheet = np.concatenate([head, sheet], 0)
    out = Path(a.out)
    with atomic_path(out) as tmp:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 82])
        Path(tmp).write_bytes(buf.tobytes())
    print(json.dumps({"frames": [int(seq.frame_index[r]) for r in rows], "gaze_x": [round(float(gx[p]), 3) for p in pos],
                      "bytes": out.stat().st_size, "size": list(sheet.shape[:2])}))


if __name__ == "__main__":
    main()
