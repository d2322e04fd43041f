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
