"""What every refused command prints: exactly one ``error: ...`` line on stderr, naming what
was wrong, and never a traceback. One check for the reliability tests."""

from __future__ import annotations


def one_error_line(err: str, *needles: str, progress: bool = False) -> str:
    """Assert ``err`` is one ``error: `` line holding every needle; with ``progress`` the
    command's ``[facesynth] ...`` progress lines before it are allowed. Returns the line."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not (progress and ln.startswith("[facesynth] "))]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    if not progress:
        assert err.startswith("error: ") and err.count("\n") == 1, err
    for needle in needles:
        assert needle in lines[0], (needle, err)
    return lines[0]
