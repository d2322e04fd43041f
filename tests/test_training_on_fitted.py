"""``run_training(..., on_fitted=)`` (the studio exports the avatar before the evaluation): the
callback runs once the model is saved and before metrics.json, and the run folder ends the same
as without it (every file, byte for byte, but the times: creation dates, seconds taken, and the
report that shows them)."""

from __future__ import annotations

import json
from pathlib import Path

from facesynth.runs.config import compose_config
from facesynth.runs.training import run_training

SMALL = ["regressor=linear", "data.n_frames=60", "data.size=96", "model.reference_width=48", "sadm.augment_copies=0",
         "sadm.region_shrink=false", "eval.noise=[0.0]", "eval.frame_level=false", "eval.train_level=false",
         "eval.talking_head=false", "quiet=true"]


TIMES = ("created", "timings_s", "fit_seconds")


def scrub(x):
    """A JSON value without its times."""
    if isinstance(x, dict):
        return {k: scrub(v) for k, v in x.items() if k not in TIMES}
    return [scrub(v) for v in x] if isinstance(x, list) else x


def files(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def test_on_fitted_runs_after_the_save_and_changes_nothing(tmp_path):
    seen = []

    def on_fitted():
        seen.append(sorted(str(p.relative_to(tmp_path / "b")) for p in (tmp_path / "b").rglob("*") if p.is_file()))

    run_training(compose_config(SMALL), tmp_path / "a")
    run_training(compose_config(SMALL), tmp_path / "b", on_fitted=on_fitted)
    assert len(seen) == 1 and "metrics.json" not in seen[0]
    assert any(f.startswith("sadm/") for f in seen[0]) and any(f.startswith("face_model/") for f in seen[0])
    a, b = files(tmp_path / "a"), files(tmp_path / "b")
    assert a.keys() == b.keys()
    differ = sorted(k for k in a if a[k] != b[k])
    assert "metrics.json" in differ  # its timings_s
    for k in differ:
        if k.endswith(".json"):
            assert scrub(json.loads(a[k])) == scrub(json.loads(b[k])), k
        else:
            assert k == "report.html", k
