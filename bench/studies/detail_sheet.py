"""Contact sheet of held-out frames at full size: real | run A | run B | ... (the face
synthesized from the frame's landmarks, pasted into the real frame with blend_face as the
app shows it, the face box cut at the video's own resolution, no scaling).

    python -m bench.studies.detail_sheet --runs RUN_TODAY RUN_NEW --labels today new \\
        --out docs/detail_interior_lp_d3.jpg [--frames 4] [--quality 80] [--driver CLIP]

The runs are train.py runs of one clip (the first run's config names the data and the
split). The frames, from the held-out segment, show what the face is judged on: the widest
open mouth (teeth), the largest head turn (nose off the jaw's centre line), and evenly spaced
others; at least 8 frames apart. Each row is labelled with its video frame and each tile's
LPIPS (the tile against the real one, resized to 224 px) when the perceptual
extra is installed. Prints one JSON line.

``--smoothed``: the frames' landmarks (and the banks' training frames) smoothed as
``data.smooth_landmarks=true`` does, whatever the runs were trained on.

``--driver CLIP``: each run driven by another person instead (a shared clip's tracked
landmarks, or an ingested folder's: a MediaPipe avatar takes a MediaPipe driver; relative
motion, the driver's neutral from its own frames): the runs exported (default export) and played through the full-frame talking head
(:class:`facesynth.runtime.Reenactor`), at the driver's widest open mouth, largest head turn
and evenly spaced frames; per row the driver's face (scaled to the tile's height) | each run's
frame, cut to the avatar's head at the video's resolution. No real frame, so no LPIPS.
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


def driven_rows(runs: list[str], driver: str, n: int) -> tuple[list[np.ndarray], list[dict]]:
    """The ``--driver`` sheet's rows: (tiles of the driver and each run, their frame's info)."""
    import tempfile

    from facesynth.data import load_sequence
    from facesynth.data.shared import shared_data_dir
    from facesynth.onnx.export import export_model
    from facesynth.runtime import Reenactor
    from facesynth.runtime.reenact import driver_neutral_of

    folder = Path(driver)
    if not folder.is_dir():  # a shared clip's name
        if shared_data_dir() is None:
            raise SystemExit("detail_sheet: ../shared/data/faces is absent")
        folder = shared_data_dir() / "faces" / driver
    dseq = load_sequence(folder)
    neutral, _ = driver_neutral_of(dseq.landmarks)
    with tempfile.TemporaryDirectory() as tmp:
        players = []
        for k, r in enumerate(runs):
            export_model(r, Path(tmp) / f"{k}.onnx", check=False)
            players.append(Reenactor(Path(tmp) / f"{k}.onnx", driver_neutral=neutral, full_frame=True))
        rows, info = [], []
        for row, why in pick(dseq.landmarks[:, :68], n):
            outs = [p.step(dseq.landmarks[row]) for p in players]
            lo, hi = outs[0][1].min(0), outs[0][1].max(0)  # the first run's avatar landmarks
            pad = 0.25 * float((hi - lo).max())
            x0, y0 = np.maximum(np.floor(lo - pad).astype(int), 0)
            h, w = outs[0][0].shape[:2]
            x1, y1 = np.minimum(np.ceil(hi + pad).astype(int), [w, h])
            d = dseq.landmarks[row, :68]
            dlo, dhi = d.min(0), d.max(0)
            dpad = 0.25 * float((dhi - dlo).max())
            frame = dseq.frame(row)
            dx0, dy0 = np.maximum(np.floor(dlo - dpad).astype(int), 0)
            dx1, dy1 = np.minimum(np.ceil(dhi + dpad).astype(int), [frame.shape[1], frame.shape[0]])
            face = frame[dy0:dy1, dx0:dx1]
            face = cv2.resize(face, (round(face.shape[1] * (y1 - y0) / face.shape[0]), y1 - y0), interpolation=cv2.INTER_AREA)
            rows.append([face] + [o[0][y0:y1, x0:x1] for o in outs])
            info.append({"frame": int(dseq.frame_index[row]), "why": why})
    return rows, info


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
    ap.add_argument("--driver", help="a shared clip (or an ingested folder) that drives every run through the talking head (no real frame)")
    ap.add_argument("--smoothed", action="store_true",
                    help="the landmarks (and the banks' training frames) smoothed as data.smooth_landmarks=true does")
    a = ap.parse_args()
    if len(a.labels) != len(a.runs):
        raise SystemExit("error: give one --labels entry per run")
    if a.driver:
        tiles, info = driven_rows(a.runs, a.driver, a.frames)
        name = Path(a.driver).name
        rows = [_row(t, f"{name} frame {i['frame']} ({i['why']})", [name] + a.labels) for t, i in zip(tiles, info, strict=True)]
        _write(rows, a.out, a.quality, {"driver": a.driver, "frames": info, "labels": a.labels})
        return
    def data(run):
        if a.smoothed:
            from bench.studies.landmark_smoothing import run_sequence

            return run_sequence(Path(run), True)[1:4]
        return run_data(read_config(run))

    seq, _, te = data(a.runs[0])
    lm_te = seq.landmarks[te][:, :68]
    chosen = pick(lm_te, a.frames)
    syns = []
    for r, strength in zip(a.runs, a.detail or [0.0] * len(a.runs), strict=True):
        sadm = load_sadm(r)
        if strength > 0:
            from bench.studies.detail import attach_bank, parse_settings

            rseq, tr, _ = data(r)
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
        labels = ["real"] + [f"{n}" + (f"  LPIPS {s:.3f}" if scores else "") for n, s in zip(a.labels, scores or [0] * len(syns),
                                                                                            strict=True)]
        rows.append(_row(tiles, f"frame {int(seq.frame_index[row])} ({why})", labels))
        info.append({"frame": int(seq.frame_index[row]), "why": why, "lpips_face": scores})
    _write(rows, a.out, a.quality, {"data": seq.name, "frames": info, "labels": a.labels})


def _row(tiles: list[np.ndarray], label: str, labels: list[str]) -> np.ndarray:
    """One labelled row of the sheet: the tiles side by side (equal heights) under a white band."""
    strip = np.concatenate([np.pad(t, ((0, 0), (0, 4), (0, 0)), constant_values=255) for t in tiles], 1)
    head = np.full((42, strip.shape[1], 3), 255, np.uint8)
    cv2.putText(head, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    x = 0
    for t, text in zip(tiles, labels, strict=True):
        cv2.putText(head, text, (x + 6, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 160), 1, cv2.LINE_AA)
        x += t.shape[1] + 4
    return np.concatenate([head, strip], 0)


def _write(rows: list[np.ndarray], out, quality: int, info: dict) -> None:
    """The rows one under the other as a JPEG at ``out`` (atomically); prints the JSON line."""
    width = max(r.shape[1] for r in rows)
    sheet = np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows], 0)
    out = Path(out)
    with atomic_path(out) as tmp:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        Path(tmp).write_bytes(buf.tobytes())
    print(json.dumps({**info, "bytes": out.stat().st_size, "size": list(sheet.shape[:2])}))


if __name__ == "__main__":
    main()
