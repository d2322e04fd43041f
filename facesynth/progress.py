"""Progress for every step that can take more than a couple of seconds: one place.

* :func:`bar` is a tqdm bar (items/s, ETA) on stderr that disappears when done; where stderr
  is not a terminal (a log, a pipe) it is a plain ``[facesynth]`` line every few seconds;
* :func:`stage` is a context manager that prints one line per finished stage with its time,
  e.g. ``[facesynth] evaluation: 60 test frames x 4 noise levels in 8.4 s``;
* :func:`set_quiet` (``--quiet`` on every command, ``quiet=true`` for ``train.py``) turns
  both off; errors and results are still printed by the callers;
* :func:`result` prints a command's result on stdout: one line for people, or its figures as
  one line of strict JSON when the command runs with ``--json`` (:func:`set_json`).

The state is process-wide on purpose: a command sets it once and every stage below it
follows, without a ``progress=`` argument threaded through each call.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

from tqdm.auto import tqdm

_QUIET = False
_JSON = False


def set_quiet(quiet: bool) -> None:
    """Silence (True) or show (False) progress bars and stage lines from here on."""
    global _QUIET
    _QUIET = bool(quiet)


def is_quiet() -> bool:
    return _QUIET


def set_json(on: bool) -> None:
    """Print results as JSON lines (True, ``--json``) or as lines for people (False) from here on."""
    global _JSON
    _JSON = bool(on)


def is_json() -> bool:
    return _JSON


def json_line(figures: dict) -> str:
    """``figures`` as one line of strict JSON; FacesynthError if a figure is not finite (a
    reader of the JSON never meets ``NaN``)."""
    try:
        return json.dumps(figures, allow_nan=False, default=str)
    except ValueError:
        from facesynth.errors import FacesynthError

        raise FacesynthError(f"a result holds a non-finite figure: {figures}") from None


def result(line: str, figures: dict) -> None:
    """One result of a command on stdout: ``line`` for a person, or ``figures`` as one
    :func:`json_line` under ``--json``. The figures are checked either way, before anything is
    printed: a non-finite one is an error, not a plausible line."""
    text = json_line(figures)
    print(text if _JSON else line, flush=True)


LOG_EVERY_S = 5.0
"""Where stderr is not a terminal, a progress bar prints one plain line at most this often."""


class _LogLines:
    """A file for tqdm that turns its redraws into ``[facesynth] ...`` lines on stderr,
    skipping the first (empty) one and the clearing ones."""

    encoding = "utf-8"

    def __init__(self):
        self.first = True

    def write(self, s: str) -> None:
        s = s.strip("\r\n ")
        if not s:
            return
        if self.first:  # the bar's initial draw (0 done)
            self.first = False
            return
        sys.stderr.write(f"[facesynth] {s}\n")

    def flush(self) -> None:
        sys.stderr.flush()


def bar(iterable: Iterable | None = None, total: int | None = None, desc: str = "", unit: str = "it",
        enabled: bool = True, **kwargs) -> tqdm:
    """A tqdm progress bar (rate in ``unit``/s) unless quiet or ``enabled`` is False.

    Leaves no line behind when it closes: the finished stage's line comes from :func:`stage`.
    On a terminal it redraws in place; where stderr is a file or a pipe (CI, batch workers,
    ``2> log``) each redraw would be a new line, so there it prints one plain line
    (``[facesynth] desc: n/total unit [elapsed<remaining, rate]``) at most every
    :data:`LOG_EVERY_S` seconds, none at the start: a long step is never silent, a short
    one adds nothing.
    """
    kwargs.setdefault("leave", False)
    if _QUIET or not enabled:
        return tqdm(iterable, total=total, desc=desc, unit=unit, disable=True, **kwargs)
    if not _isatty(sys.stderr):
        kwargs.pop("dynamic_ncols", None)
        return tqdm(iterable, total=total, desc=desc, unit=unit, file=_LogLines(), mininterval=LOG_EVERY_S,
                    maxinterval=LOG_EVERY_S, ascii=True,
                    bar_format="{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}]", **kwargs)
    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(iterable, total=total, desc=desc, unit=unit, file=sys.stderr, **kwargs)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def note(message: str) -> None:
    """Print one informational line on stderr (unless quiet)."""
    if not _QUIET:
        tqdm.write(f"[facesynth] {message}", file=sys.stderr)


class _Stage:
    def __init__(self, name: str):
        self.name = name
        self.detail = ""
        self.seconds = 0.0

    def set(self, detail: str) -> None:
        """What the stage did, shown after its name on the finishing line."""
        self.detail = detail


@contextmanager
def stage(name: str) -> Iterator[_Stage]:
    """Time a stage and print ``name[: detail] in X s`` when it finishes (not on error)."""
    st = _Stage(name)
    t0 = time.perf_counter()
    yield st
    st.seconds = time.perf_counter() - t0
    note(f"{name}{': ' + st.detail if st.detail else ''} in {st.seconds:.1f} s")
