"""Does the studio's coverage meter predict held-out quality? For each shared clip: MediaPipe's 478
points (``facesynth ingest --landmarker mediapipe``), split as training splits it (the first
75 % trains), and

* ``heldout``: the meter's reach of the held-out frames by the training frames
  (``facesynth.web.coverage.heldout_coverage``: the shapes to render are the held-out ones);
* ``prior``: the page's overall coverage of the training frames (the prior's directions; the
  neutral: the median over those frames, as for a recording without a neutral prompt);

against the clip's held-out PSNR with mediapipe478 (whole face and mouth interior, sigma 0) from
the tables of docs/landmarks.md. Prints ONE JSON line: per clip, and Spearman's rank correlation
of each measure with each PSNR.

    python -m bench.studies.coverage_heldout [--ingested DIR]   (DIR/CLIP: ingest folders to reuse)
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
    import argparse

    from scipy.stats import spearmanr

    from facesynth.data import temporal_split
    from facesynth.data.ingest import ingest_video
    from facesynth.data.shared import shared_data_dir
    from facesynth.web.coverage import coverage, heldout_coverage

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ingested", help="a folder of mediapipe ingest folders, one per clip (made when missing)")
    a = p.parse_args()

    md = (Path(__file__).resolve().parents[2] / "docs" / "landmarks.md").read_text()
    whole = {r[0]: float(r[4]) for r in table(md, "| clip | frames | detection rate: MediaPipe")}
    mouth = {r[0]: float(re.split(r"\s*/\s*", r[2])[1].split()[0]) for r in table(md, "| clip | eyes | mouth interior")}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(a.ingested or tmp)
        for clip in sorted(whole):
            video = shared_data_dir() / "faces" / clip / "video.mp4"
            if not (where / clip / "landmarks.npy").is_file():
                ingest_video(video, where / clip, landmarker="mediapipe")
            lm = np.load(where / clip / "landmarks.npy")  # (T, 478, 2), every frame with a face on these clips
            tr, te = temporal_split(len(lm))
            c = coverage([{"id": "train", "directions": [], "points": list(lm[tr])}])
            out[clip] = {"heldout": round(heldout_coverage(lm[tr], lm[te]), 3),
                         "prior": round(c["overall"], 3), "psnr_whole": whole[clip], "psnr_mouth": mouth.get(clip),
                         "directions": {k: round(v, 2) for k, v in c["directions"].items()}}
    clips = [k for k in out if out[k]["psnr_mouth"] is not None]
    rho = {f"spearman_{m}_{q}": round(float(spearmanr([out[k][m] for k in clips], [out[k][f"psnr_{q}"] for k in clips])[0]), 3)
           for m in ("heldout", "prior") for q in ("whole", "mouth")}
    print(json.dumps({"clips": out, **rho, "n": len(clips)}))


if __name__ == "__main__":
    main()
