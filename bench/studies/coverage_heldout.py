"""Does the studio's coverage meter predict held-out quality? For each shared clip: MediaPipe's 478
points (``facesynth ingest --landmarker mediapipe``), the meter's overall coverage of its
training part (the first 75 %, the split training uses; the neutral: the median over those
frames, as for a recording without a neutral prompt), and the clip's held-out PSNR with
mediapipe478 (whole face and mouth interior, sigma 0) from the table of docs/landmarks.md.
Prints ONE JSON line: per clip, and Spearman's rank correlation of coverage with each PSNR.

    python -m bench.studies.coverage_heldout
"""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import numpy as np


def table(md: str, header_start: str) -> list[list[str]]:
    lines = md.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def main() -> None:
    from scipy.stats import spearmanr

    from facesynth.data import temporal_split
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_data_dir
    from facesynth.web.coverage import coverage

    md = (Path(__file__).resolve().parents[2] / "docs" / "landmarks.md").read_text()
    whole = {r[0]: float(r[4]) for r in table(md, "| clip | frames | detection rate: MediaPipe")}
    mouth = {r[0]: float(re.split(r"\s*/\s*", r[2])[1].split()[0]) for r in table(md, "| clip | eyes | mouth interior")}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for clip in sorted(whole):
            video = shared_data_dir() / "faces" / clip / "video.mp4"
            seq = ingest_video(video, Path(tmp) / clip, landmarker="mediapipe")
            tr, _ = temporal_split(len(seq))
            c = coverage([{"id": "train", "directions": [], "points": list(seq.landmarks[tr])}])
            out[clip] = {"coverage": round(c["overall"], 3), "psnr_whole": whole[clip], "psnr_mouth": mouth.get(clip),
                         "directions": {k: round(v, 2) for k, v in c["directions"].items()}}
    clips = [k for k in out if out[k]["psnr_mouth"] is not None]
    cov = np.array([out[k]["coverage"] for k in clips])
    print(json.dumps({"clips": out,
                      "spearman_whole": round(float(spearmanr(cov, [out[k]["psnr_whole"] for k in clips])[0]), 3),
                      "spearman_mouth": round(float(spearmanr(cov, [out[k]["psnr_mouth"] for k in clips])[0]), 3),
                      "n": len(clips)}))


if __name__ == "__main__":
    main()
