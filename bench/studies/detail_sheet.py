"""Contact sheet of held-out frames at full size: real | run A | run B | ... (the face
synthesized from the frame's landmarks, pasted into the real frame with blend_face as the
app shows it, the face box cut at the video's own resolution, no scaling).

    python -m bench.studies.detail_sheet --runs RUN_TODAY RUN_NEW --labels today new \\
        --out docs/detail_interior_lp_d3.jpg [--frames 4] [--quality 80]

The runs are train.py runs of one clip (the first run's config names the data and the
split). The frames, from the held-out segment, show what the face is judged on: the widest
open mouth (teeth), the largest head turn (nose off the jaw's centre line), and evenly spaced
others; at least 8 frames apart. Each row is labelled with its video frame and each tile's
LPIPS (the tile against the real one, resized to 224 px) when the perceptual
extra is installed. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from facesynth.compositing import blend_rendered
from facesynth.eval import perceptual
from facesynth.io import atomic_path
from facesynth.rundir import read_config, run_data
from facesynth.sadm.fit import load_sadm


def pick(lm: np.ndarray, n: int, gap: int = 8) -> list[tuple[int, str]]:
    """(position, why) of ``n`` held-out frames: widest mouth, largest turn, then evenly spaced."""
    iod = np.linalg.norm(lm[:, 45] - lm[:, 36], axis=1)
    mouth = np.linalg.norm(lm[:, 66] - lm[:, 62], axis=1) / iod
    turn = np.abs(lm[:, 30, 0] - 0.5 * (lm[:, 0, 0] + lm[:, 16, 0])) / iod
    out: list[tuple[int, str]] = []
    for score, why in ((mouth, "open mouth"), (turn, "head turn")):
        for i in np.argsort(-score):
            if all(abs(int(i) - j) >= gap for j, _ in out):
                out.append((int(i), why))
                break
    for i in np.linspace(0, len(lm) - 1, n + 2)[1:-1].round().astype(int):
        if len(out) >= n:
            break
        if all(abs(int(i) - j) >= gap for j, _ in out):
            out.append((int(i), "evenly spaced"))
    return out[:n]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--labels", nargs="+", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--quality", type=int, default=80)
    ap.add_argument("--detail", nargs="+", type=float, default=None,
                    help="per run: the example-based detail's strength, its bank fitted on the run's training frames "
                         "as bench/studies/detail.py does (0: the run as trained)")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE of model.detail_* for the banks")
    a = ap.parse_args()
    if len(a.labels) != len(a.runs):
        raise SystemExit("error: give one --labels entry per run")
    seq, _, te = run_data(read_config(a.runs[0]))
    lm_te = seq.landmarks[te][:, :68]
    chosen = pick(lm_te, a.frames)
    syns = []
    for r, strength in zip(a.runs, a.detail or [0.0] * len(a.runs), strict=True):
        sadm = load_sadm(r)
        if strength > 0:
            from bench.studies.detail import attach_bank, parse_settings

            rseq, tr, _ = run_data(read_config(r))
            attach_bank(sadm, rseq, tr, parse_settings(a.set), strength)
        syns.append(sadm.synthesizer())
    rows, info = [], []
    for pos, why in chosen:
        row = int(te[pos])
        frame = seq.frame(row)
        lm = seq.landmarks[row : row + 1]
        p = lm[0, :68]
        lo, hi = p.min(0), p.max(0)
        pad = 0.12 * float((hi - lo).max())
        x0, y0 = np.maximum(np.floor(lo - pad).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(hi + pad).astype(int), [frame.shape[1], frame.shape[0]])
        tiles, scores = [frame[y0:y1, x0:x1]], []
        for syn in syns:
            with torch.no_grad():
                crops, masks, places = (t.numpy() for t in syn(torch.from_numpy(lm[:, : syn.n_points].copy())))
            shown = blend_rendered(crops, masks, places, frame)[y0:y1, x0:x1]
            tiles.append(shown)
            if perceptual.available():
                scores.append(float(perceptual.lpips(perceptual.region_crop(tiles[0], (0, y1 - y0, 0, x1 - x0)),
                                                     perceptual.region_crop(shown, (0, y1 - y0, 0, x1 - x0)))[0]))
        strip = np.concatenate([np.pad(t, ((0, 0), (0, 4), (0, 0)), constant_values=255) for t in tiles], 1)
        label = f"frame {int(seq.frame_index[row])} ({why})"
        labels = ["real"] + [f"{n}" + (f"  LPIPS {s:.3f}" if scores else "") for n, s in zip(a.labels, scores or [0] * len(syns),
                                                                                            strict=True)]
        head = np.full((42, strip.shape[1], 3), 255, np.uint8)
        cv2.putText(head, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        w = tiles[0].shape[1] + 4
        for k, t in enumerate(labels):
            cv2.putText(head, t, (k * w + 6, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 160), 1, cv2.LINE_AA)
        rows.append(np.concatenate([head, strip], 0))
        info.append({"frame": int(seq.frame_index[row]), "why": why, "lpips_face": scores})
    width = max(r.shape[1] for r in rows)
    sheet = np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows], 0)
    out = Path(a.out)
    with atomic_path(out) as tmp:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, a.quality])
        Path(tmp).write_bytes(buf.tobytes())
    print(json.dumps({"data": seq.name, "frames": info, "labels": a.labels, "bytes": out.stat().st_size,
                      "size": list(sheet.shape[:2])}))


if __name__ == "__main__":
    main()
