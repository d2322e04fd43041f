"""One ``train.py`` per run folder: a lock file held while a run writes there.

``RUN/.train.lock`` holds the pid of the run that owns the folder, locked with
``fcntl.flock``. The kernel drops the lock when its process ends, however it ends, so a lock
file left by a killed run (SIGKILL, power loss) is taken over by the next run; a live
holder makes the second run refuse, naming the folder and the pid. The file is removed
when the run ends (:func:`release_run_dirs`, also at interpreter exit).
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
from pathlib import Path

from facesynth.errors import FacesynthError

LOCK_NAME = ".train.lock"
_HELD: dict[str, tuple[int, Path, bool]] = {}  # realpath -> (fd, lock file, folder created by us)


def _holder(path: Path) -> str:
    with contextlib.suppress(OSError, ValueError):
        return str(int(path.read_text().split()[0]))
    return "unknown"


def lock_run_dir(run_dir: str | os.PathLike) -> Path:
    """Lock ``run_dir`` for this process (created when absent; taking a lock it already
    holds is a no-op). Returns the lock file.

    Raises
    ------
    FacesynthError
        Another live process holds the folder.
    """
    d = Path(run_dir)
    key = os.path.realpath(d)
    if key in _HELD:
        return _HELD[key][1]
    created = not d.exists()
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FacesynthError(f"{d}: cannot create the run folder ({exc.strerror})") from None
    path = d / LOCK_NAME
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise FacesynthError(f"{d}: run folder in use by another train.py (pid {_holder(path)}); wait for it "
                                 "to end or choose another hydra.run.dir") from None
        try:  # its previous holder may have removed the file between our open and flock: lock the new one
            current = os.stat(path)
        except FileNotFoundError:
            current = None
        if current is not None and os.path.samestat(os.fstat(fd), current):
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    if not _HELD:
        atexit.register(release_run_dirs)
    _HELD[key] = (fd, path, created)
    return path


def discard_unused_run_dir(run_dir: str | os.PathLike, keep_if_other_than: set[str]) -> bool:
    """Remove ``run_dir`` when this process created it (its lock says so) and it holds
    nothing but the names in ``keep_if_other_than`` (Hydra's ``.hydra/`` and log) and the
    lock: a run refused before it wrote anything leaves no folder. Returns whether it did."""
    import shutil

    key = os.path.realpath(run_dir)
    if key not in _HELD or not _HELD[key][2]:
        return False
    d = Path(run_dir)
    if not {p.name for p in d.iterdir()} <= keep_if_other_than | {LOCK_NAME}:
        return False
    fd, _, _ = _HELD.pop(key)
    shutil.rmtree(d, ignore_errors=True)
    os.close(fd)
    return True


def release_run_dirs() -> None:
    """Remove this process's lock files and release the locks (a folder this process
    created and left empty is removed too)."""
    while _HELD:
        _, (fd, path, created) = _HELD.popitem()
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)
        if created:
            with contextlib.suppress(OSError):
                path.parent.rmdir()  # only when empty
