"""Does the studio's coverage meter predict held-out quality? For each shared clip: MediaPipe's 478
points (``facesynth ingest --landmarker mediapipe``), split as training splits it (the first
75 % trains: the "recording"), the recording thinned to the frames the page keeps (at most
``KEEP_FPS`` a second, the page's rule), and

* ``self_reach``: the page's headline, the recording's reach of itself, one-second blocks held
  out in turn (``facesynth.web.coverage.self_reach``);
* ``self_reach_eighths``: the same with blocks of an eighth of the recording (0.3-3.2 s on
  these clips, 5 s on a 40 s recording), nearer the held-out split's size;
* ``prior``: the page's mean reach of its 13 prior directions (the neutral: the median over the
  recording, as for a recording without a neutral prompt);
* ``spread``: the recording's mean distance from its mean shape, in the meter's units (how lively
  it is: the baseline a reading has to beat);
* ``heldout``: the reach of the clip's held-out frames by its training frames
  (``heldout_coverage``; the page cannot know these: the ceiling);

against the clip's held-out quality from the tables of the docs: whole-face PSNR with
mediapipe478 (sigma 0, docs/landmarks.md) and the default model's ``psnr_frame_common``, face
LPIPS and mouth LPIPS (docs/eval.md). Prints ONE JSON line: per clip, then per reading and
target Spearman's and Pearson's correlation, a 95 % bootstrap interval of Spearman's (the 17
clips resampled 2000 times, seed 0) and its range leaving one clip out.

    python -m bench.studies.coverage_heldout [--ingested DIR]   (DIR/CLIP: ingest folders to reuse)
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from bench.harness import emit, host

DOCS = Path(__file__).resolve().parents[2] / "docs"


def table(md: str, header_start: str) -> list[list[str]]:
    lines = md.splitlines()
    i = next((k for k, line in enumerate(lines) if line.startswith(header_start)), None)
    if i is None:
        raise SystemExit(f"no table starting {header_start!r} in the docs")
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def targets() -> dict[str, dict[str, float]]:
    """Held-out quality per clip: target name -> {clip: value}."""
    lm = table((DOCS / "landmarks.md").read_text(), "| clip | frames | detection rate: MediaPipe")
    ev = table((DOCS / "eval.md").read_text(), "| clip | face LPIPS | eyes LPIPS | mouth LPIPS | psnr_frame_common")
    return {"psnr_mediapipe478": {r[0]: float(r[4]) for r in lm},
            "psnr_default": {r[0]: float(r[4]) for r in ev},
            "lpips_face_default": {r[0]: float(r[1]) for r in ev},
            "lpips_mouth_default": {r[0]: float(r[3]) for r in ev}}


def kept(n: int, fps: float, keep_fps: float) -> np.ndarray:
    """Indices of the frames the page keeps of ``n`` camera frames at ``fps``: a frame when at
    least 1/keep_fps - 2 ms passed since the last kept one (studio.js's rule)."""
    out, last = [], -1e9
    for i in range(n):
        t = i / fps
        if t - last >= 1 / keep_fps - 0.002:
            out.append(i)
            last = t
    return np.asarray(out)


def correlations(x: list[float], y: list[float], rng: np.random.Generator, n_boot: int = 2000) -> dict:
    from scipy.stats import pearsonr, spearmanr

    x, y = np.asarray(x), np.asarray(y)
    boot = []
    for _ in range(n_boot):
        i = rng.integers(0, len(x), len(x))
        if np.ptp(x[i]) > 0 and np.ptp(y[i]) > 0:
            boot.append(spearmanr(x[i], y[i])[0])
    loo = [spearmanr(np.delete(x, i), np.delete(y, i))[0] for i in range(len(x))]
    return {"spearman": round(float(spearmanr(x, y)[0]), 3), "pearson": round(float(pearsonr(x, y)[0]), 3),
            "spearman_95": [round(float(v), 2) for v in np.percentile(boot, [2.5, 97.5])],
            "spearman_leave_one_out": [round(float(min(loo)), 2), round(float(max(loo)), 2)]}


def main() -> None:
    import argparse

    from facesynth.data import temporal_split
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_data_dir
    from facesynth.web.coverage import KEEP_FPS, SCALE, coverage, features, heldout_coverage, self_reach

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ingested", help="a folder of mediapipe ingest folders, one per clip (made when missing)")
    a = p.parse_args()

    tg = targets()
    clips = sorted(set.intersection(*(set(t) for t in tg.values())))
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(a.ingested or tmp)
        for clip in clips:
            if not (where / clip / "landmarks.npy").is_file():
                ingest_video(shared_data_dir() / "faces" / clip / "video.mp4", where / clip, landmarker="mediapipe")
            lm = np.load(where / clip / "landmarks.npy")  # (T, 478, 2), every frame with a face on these clips
            fps = json.loads((where / clip / "meta.json").read_text())["video"]["fps"]
            tr, te = temporal_split(len(lm))
            rec = lm[tr][kept(len(tr), fps, KEEP_FPS)]
            c = coverage([{"id": "recording", "directions": [], "points": list(rec)}])
            f = features(rec)
            z = f / np.asarray(SCALE)
            out[clip] = {"frames_kept": len(rec), "self_reach": round(c["self_reach"], 3),
                         "self_reach_eighths": round(self_reach(f, -(-len(rec) // 8)), 3), "prior": round(c["overall"], 3),
                         "spread": round(float(np.linalg.norm(z - z.mean(0), axis=1).mean()), 3),
                         "heldout": round(heldout_coverage(lm[tr], lm[te]), 3),
                         **{k: v[clip] for k, v in tg.items()}, "directions": {k: round(v, 2) for k, v in c["directions"].items()}}
    rng = np.random.default_rng(0)
    corr = {m: {t: correlations([out[k][m] for k in clips], [out[k][t] for k in clips], rng) for t in tg}
            for m in ("self_reach", "self_reach_eighths", "prior", "spread", "heldout")}
    emit({"bench": "coverage_heldout", **host(), "n": len(clips), "keep_fps": KEEP_FPS, "clips": out, "correlations": corr})


if __name__ == "__main__":
    main()
