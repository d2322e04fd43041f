"""What "the dense scheme beats ibug68 by 1 dB over the common region" needs, region by region.

Reads the ``metrics.json`` of pairs of ``train.py`` runs of the same clip (a dense-scheme run
and an ``ibug68`` run, both with the frame-level evaluation and its common region) and prints,
per clip, :func:`facesynth.eval.regions_gap.scheme_gap` at sigma 0: both whole figures, the
target, the dense run's whole figure with its eyes and mouth interior at its PCA oracle, and
the ``rest`` figure the target would need (with the eyes and mouth interior as predicted, and
at the oracle) next to the ``rest`` of both runs and the dense run's ``rest`` oracle.
Prints ONE JSON line.

    python -m bench.studies.scheme_gap --dense RUN_MP/lp_d6 RUN_MP/lp_d10 --base RUN_IB/lp_d6 RUN_IB/lp_d10 [--margin 1]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main() -> None:
    from bench.harness import add_scheme_pairs, scheme_pairs
    from facesynth.errors import FacesynthError
    from facesynth.eval.regions_gap import scheme_gap

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_scheme_pairs(p)
    p.add_argument("--margin", type=float, default=1.0, help="dB the dense scheme must gain (issue 14: 1.0)")
    a = p.parse_args()
    out = {}
    for d, b, md, mb in scheme_pairs(a):
        try:
            gap = scheme_gap(md, mb, a.margin, where=(f"{d}/metrics.json", f"{b}/metrics.json"))
        except FacesynthError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
        clip = md.get("data", {}).get("name", Path(d).name)
        out[clip] = {k: (round(v, 3) if isinstance(v, float) else {s: round(x, 4) for s, x in v.items()})
                     for k, v in gap.items()}
        out[clip]["schemes"] = [md.get("landmark_scheme"), mb.get("landmark_scheme")]
    print(json.dumps({"bench": "scheme_gap", "margin_db": a.margin, "clips": out}))


if __name__ == "__main__":
    main()
