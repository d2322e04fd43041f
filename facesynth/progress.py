"""Progress for every step that can take more than a couple of seconds: one place.

* :func:`bar` is a tqdm bar (items/s, ETA) on stderr that disappears when done (terminals only);
* :func:`stage` is a context manager that prints one line per finished stage with its time,
  e.g. ``[facesynth] evaluation: 60 test frames x 4 noise levels in 8.4 s``;
* :func:`set_quiet` (``--quiet`` on every command, ``quiet=true`` for ``train.py``) turns
  both off; errors and results are still printed by the callers.

The state is process-wide on purpose: a command sets it once and every stage below it
follows, without a ``progress=`` argument threaded through each call.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

from tqdm.auto import tqdm

_QUIET = False


def set_quiet(quiet: bool) -> None:
    """Silence (True) or show (False) progress bars and stage lines from here on."""
    global _QUIET
    _QUIET = bool(quiet)


def is_quiet() -> bool:
    return _QUIET


def bar(iterable: Iterable | None = None, total: int | None = None, desc: str = "", unit: str = "it",
        enabled: bool = True, **kwargs) -> tqdm:
    """A tqdm progress bar (rate in ``unit``/s) unless quiet or ``enabled`` is False.

    Leaves no line behind when it closes: the finished stage's line comes from :func:`stage`.
    Only on a terminal: when stderr is a file or a pipe (CI, batch workers, ``2> log``) the
    bar is off (tqdm's ``disable=None``), since each redraw would be a new line there; the
    stage lines still say what finished and how long it took.
    """
    kwargs.setdefault("leave", False)
    kwargs.setdefault("dynamic_ncols", True)
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=True if _QUIET or not enabled else None,
                file=sys.stderr, **kwargs)


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
