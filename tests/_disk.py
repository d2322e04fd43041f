"""A real full disk for the reliability tests: a small tmpfs filled with dd (root only; the
test skips where it cannot mount one)."""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path

import pytest


@contextlib.contextmanager
def full_tmpfs(where: Path, size: str = "2M", leave_kb: int = 0):
    """A tmpfs of ``size`` mounted at ``where`` (created), filled by the file ``filler`` up to
    ``leave_kb`` KiB free; unmounted on the way out."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    where.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        subprocess.run(["dd", "if=/dev/zero", f"of={where / 'filler'}", "bs=4k"], capture_output=True)
        if leave_kb:
            with open(where / "filler", "r+b") as f:
                f.truncate(max(0, os.path.getsize(where / "filler") - leave_kb * 1024))
        yield where
    finally:
        subprocess.run(["umount", str(where)], capture_output=True)
