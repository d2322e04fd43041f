"""A newcomer's first commands: the top-level help says how to train, ingest shows progress
where it is not a terminal, and a deliberately limited ingest is not reported as landmarks
of a shorter clip."""

from __future__ import annotations

import subprocess
import sys


def test_top_level_help_says_how_to_train():
    for argv in (["--help"], []):  # no arguments: the same help
        out = subprocess.run([sys.executable, "-m", "facesynth", *argv], capture_output=True, text=True)
        assert out.returncode == 0 and out.stderr == ""
        text = out.stdout
        assert "python train.py" in text and "python train.py data=video data.path=DIR" in text
        assert text.index("python train.py") < text.index("subcommands:")  # training before the subcommands
