"""A newcomer's first commands: the top-level help says how to train, ingest shows progress
where it is not a terminal, and a deliberately limited ingest is not reported as landmarks
of a shorter clip."""

from __future__ import annotations

import subprocess
import sys

import pytest
from test_reliability_io import fake_ingest  # noqa: F401
from test_reliability_outputs import cli_ingest  # noqa: F401 - fixtures

from facesynth.cli import main


def test_top_level_help_says_how_to_train():
    for argv in (["--help"], []):  # no arguments: the same help
        out = subprocess.run([sys.executable, "-m", "facesynth", *argv], capture_output=True, text=True)
        assert out.returncode == 0 and out.stderr == ""
        text = out.stdout
        assert "facesynth train" in text and "facesynth train data=video data.path=DIR" in text
        assert text.index("facesynth train") < text.index("subcommands:")  # training before the subcommands
        subcommands = text[text.index("subcommands:"):].splitlines()[1:]
        assert subcommands[0].split()[0] == "train"  # listed first


@pytest.mark.parametrize("quiet", [False, True])
def test_ingest_shows_progress_where_stderr_is_not_a_terminal(cli_ingest, tmp_path, capsys, monkeypatch, quiet):  # noqa: F811
    """Captured stderr is not a terminal (a log, a pipe): ingest still says what it does and
    how far it is (one line at most every progress.LOG_EVERY_S seconds; 0 here: every frame)."""
    from facesynth import progress

    path, det, calls = cli_ingest
    monkeypatch.setattr(progress, "LOG_EVERY_S", 0.0)
    try:
        assert main(["ingest", str(path), "--out", str(tmp_path / "d")] + (["--quiet"] if quiet else [])) == 0
    finally:
        progress.set_quiet(False)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("[facesynth] ingest:")]
    if quiet:
        assert lines == [] and err == ""
    else:
        assert lines[0].startswith(f"[facesynth] ingest: {path} (128x128, 6 frames) with dlib")
        assert lines[-1].startswith("[facesynth] ingest: 6/6 frame [")
        assert len(lines) >= 2


def test_readme_main_job_runs_as_written(tmp_path):
    """README's Getting started, step 2 (``facesynth train``, the default configuration on the
    built-in synthetic subject) trains, evaluates and writes its report."""
    import json
    import os
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    step = (root / "README.md").read_text().split("**2. Run the main job**")[1].split("**3.")[0]
    command = re.search(r"```bash\n(.*?)\s*(#.*)?\n```", step, re.S).group(1).strip()
    assert command == "facesynth train"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "facesynth", "train", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["regressor"] == "krr"
    assert metrics["psnr_ref"]["sadm"]["0"] > metrics["psnr_ref"]["mean_texture"]["0"]
    assert (tmp_path / "run" / "report.html").stat().st_size > 1000
