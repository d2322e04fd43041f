"""Atomic file writing: outputs appear whole or not at all.

Temporary files and folders are siblings of their target named
``.NAME.facesynth-tmp-PID-XXXXXXXX[.ext]``, so that they are recognisably ours. They are
removed on any exception (the CLI turns SIGTERM into an exception, see
:func:`install_sigterm_handler`); one left by a killed process (SIGKILL, power loss) is
removed by the next write into the same folder once its process is gone (each folder is
scanned once per process).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import signal
import tempfile
from pathlib import Path
from typing import Any, Iterator

TMP_TAG = ".facesynth-tmp-"
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
"""``OSError.errno`` values that mean the disk (or the user's quota) is full."""


def is_disk_full(exc: BaseException) -> bool:
    """True for an OSError saying the disk or quota is full."""
    return isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS


def _disk_full_error(path: Path):
    from facesynth.errors import DiskFullError

    return DiskFullError(path)


def refuse_overwriting_inputs(outputs, inputs) -> None:
    """FacesynthError, before any work, when an output path is one of the inputs (same
    file by ``os.path.samefile``, or the same resolved path) or a folder that holds one
    (an output folder is replaced as a whole). ``None`` entries are skipped.

    Parameters
    ----------
    outputs, inputs : iterable of path-like or None
    """
    from facesynth.errors import FacesynthError

    ins = [Path(p) for p in inputs if p is not None]
    for out in (Path(p) for p in outputs if p is not None):
        real_out = os.path.realpath(out)
        for inp in ins:
            real_in = os.path.realpath(inp)
            same = real_in == real_out
            if not same and out.exists() and inp.exists():
                with contextlib.suppress(OSError):
                    same = os.path.samefile(out, inp)
            if same:
                raise FacesynthError(f"{out}: the output is the input {inp}; writing it would destroy the input "
                                     "(choose another output path)")
            if out.is_dir() and real_in.startswith(real_out.rstrip(os.sep) + os.sep):
                raise FacesynthError(f"{out}: the output folder holds the input {inp} and would be replaced as a "
                                     "whole (choose another output folder)")


def _tmp_prefix(path: Path) -> str:
    return f".{path.name}{TMP_TAG}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    return True


_SCANNED: set[str] = set()  # folders already cleaned by this process (one scan each: writes of many files stay linear)


def remove_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and folders that dead facesynth processes left beside
    ``path`` (in its folder); returns them. Each folder is scanned once per process."""
    folder = Path(path).parent
    key = os.path.abspath(folder)
    removed: list[Path] = []
    if key in _SCANNED or not folder.is_dir():
        return removed
    _SCANNED.add(key)
    for entry in os.scandir(folder):
        name = entry.name
        if not name.startswith(".") or TMP_TAG not in name:
            continue
        pid_text = name.split(TMP_TAG, 1)[1].split("-", 1)[0]
        if not pid_text.isdigit() or int(pid_text) == os.getpid() or _pid_alive(int(pid_text)):
            continue  # not ours, or a write in progress (this process's or a live one's)
        p = Path(entry.path)
        with contextlib.suppress(OSError):
            shutil.rmtree(p) if entry.is_dir(follow_symlinks=False) else p.unlink()
            removed.append(p)
    return removed


def remove_dead_pid_folders(root: str | os.PathLike, prefix: str) -> list[Path]:
    """Remove the folders ``root/PREFIX<PID>-*`` of this user whose process ``PID`` is gone (a
    server or job killed before it cleaned up); returns them. Folders of live processes, of
    other users, links and other names stay."""
    removed = []
    for d in Path(root).glob(prefix + "*-*"):
        pid = d.name[len(prefix):].split("-", 1)[0]
        if not pid.isdigit() or d.is_symlink() or not d.is_dir() or d.stat().st_uid != os.getuid() or _pid_alive(int(pid)):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def set_default_mode(path: str | os.PathLike) -> None:
    """Give the file ``path`` the usual permissions (0666 & ~umask), whatever its writer created
    it with (some write 0600)."""
    os.chmod(path, 0o666 & ~_umask())


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    Parameters
    ----------
    path : path-like
        Final destination. Its parent folder is created.
    suffix : str, optional
        Suffix of the temporary file (defaults to that of ``path``, so that writers
        which choose a format by extension, e.g. ``cv2.VideoWriter``, still work).
        Writers that append their own suffix to a name (``np.save``) must write to an
        open file object instead (see :func:`save_npy`).

    On any exception (SIGTERM included, once :func:`install_sigterm_handler` is active)
    the temporary file is removed and ``path`` is left untouched. The written file gets
    the usual permissions (0666 & ~umask) whatever the writer created it with.
    """
    path = Path(path)
    created = _check_parent(path)
    remove_stale_temps(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{_tmp_prefix(path)}{os.getpid()}-",
                                   suffix=path.suffix if suffix is None else suffix, dir=path.parent)
    except OSError as exc:
        _remove_empty(created)
        if is_disk_full(exc):
            raise _disk_full_error(path) from None
        raise
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # some writers (safetensors) replace the file: set the mode on what was written
        set_default_mode(tmp_path)
        os.replace(tmp_path, path)
    except BaseException as exc:
        from facesynth.errors import DiskFullError

        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        _remove_empty(created)
        # a writer of the temporary file may itself write atomically: it names the temporary
        if is_disk_full(exc) or (isinstance(exc, DiskFullError) and str(exc.path) == str(tmp_path)):
            raise _disk_full_error(path) from None
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces ``path`` as a whole.

    The folder appears complete or not at all: an existing ``path`` is first renamed
    aside (a hidden ``.NAME.facesynth-tmp-PID-old-...`` sibling), the new folder is
    renamed onto ``path``, then the old one is removed. On any exception the temporary
    folder is removed and ``path`` is untouched.
    """
    path = Path(path)
    created = _check_parent(path)
    remove_stale_temps(path)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f"{_tmp_prefix(path)}{os.getpid()}-", dir=path.parent))
    except OSError as exc:
        _remove_empty(created)
        if is_disk_full(exc):
            raise _disk_full_error(path) from None
        raise
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        if path.exists() or path.is_symlink():
            old = Path(tempfile.mkdtemp(prefix=f"{_tmp_prefix(path)}{os.getpid()}-old-", dir=path.parent))
            try:
                os.replace(path, old)
            except BaseException:
                os.rmdir(old)  # path could not be moved aside (a file onto a folder): no hidden leftover
                raise
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException as exc:
        from facesynth.errors import DiskFullError

        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)
        # name the file being written inside the folder (as it would be under ``path``) when known
        if is_disk_full(exc):
            raise _disk_full_error(_in_folder(exc.filename, tmp, path)) from None
        if isinstance(exc, DiskFullError):
            raise _disk_full_error(_in_folder(exc.path, tmp, path)) from None
        raise


def _in_folder(filename, tmp: Path, path: Path) -> Path:
    """``filename`` (inside the temporary folder ``tmp``) as it would be under ``path``."""
    if filename:
        with contextlib.suppress(ValueError):
            return path / Path(filename).relative_to(tmp)
    return path


def _check_parent(path: Path) -> list[Path]:
    """Create ``path``'s parent; FacesynthError when it cannot be (a file on the way, no
    permission). Returns the folders it created, deepest last (removed again, when empty, by
    a write that fails: a refused or failed run leaves no empty folders)."""
    from facesynth.errors import FacesynthError

    missing = []
    parent = path.parent
    while not parent.exists() and not parent.is_symlink() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        _remove_empty(missing[::-1])
        raise FacesynthError(f"{path}: cannot write here (a parent is a file, not a folder)") from None
    except PermissionError:
        _remove_empty(missing[::-1])
        raise FacesynthError(f"{path}: cannot write here (permission denied creating {path.parent})") from None
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise FacesynthError(f"{path}: cannot write here ({path.parent} is not writable)")
    return missing[::-1]


def _remove_empty(created: list[Path]) -> None:
    """Remove the folders :func:`_check_parent` created (deepest first) while they are empty."""
    for folder in reversed(created):
        try:
            folder.rmdir()
        except OSError:
            return  # not empty (another output went there) or already gone: keep it and its parents


def check_writable(path: str | os.PathLike, folder: bool = False) -> Path:
    """Check, before any work, that ``path`` can be written: the target is not a folder
    (``folder=False``) or not a file (``folder=True``); a file name is not written with a
    trailing ``/`` and is not an existing device, pipe or socket (``/dev/null`` is never
    replaced); and its nearest existing ancestor is a writable folder (missing parents are created later, by the write itself, so a failed
    run leaves no empty folders). Raises FacesynthError naming ``path``."""
    from facesynth.errors import FacesynthError

    text = os.fspath(path)
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise FacesynthError(f"{path}: output exists and is not a folder")
    if not folder and path.is_dir():
        raise FacesynthError(f"{path}: output is an existing folder, expected a file name")
    if not folder and text.endswith(("/", os.sep)):
        raise FacesynthError(f"{text}: output ends with '/', a folder name; expected a file name")
    if not folder and path.exists() and not path.is_file():
        raise FacesynthError(f"{path}: output exists and is not a regular file (a device, pipe or socket); "
                             "it is never replaced: choose another name")
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise FacesynthError(f"{path}: cannot write here ({parent} is a file, not a folder)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise FacesynthError(f"{path}: cannot write here ({parent} is not writable)")
    return path


def save_npy(path: str | os.PathLike, array) -> None:
    """``np.save`` to exactly ``path`` (no ``.npy`` appended), atomically."""
    import numpy as np

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)


def read_json_object(path: str | os.PathLike) -> dict:
    """The JSON object in ``path``; FacesynthError naming the file when it is unreadable,
    not JSON, or not an object."""
    from facesynth.errors import FacesynthError

    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FacesynthError(f"{path}: invalid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise FacesynthError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    return doc


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (NaN is rejected, before anything is written)."""
    write_text(path, dumps_json(obj))


def dumps_json(obj: Any) -> str:
    """``obj`` as indented strict JSON (numpy scalars and arrays, paths converted);
    FacesynthError naming the first non-finite value."""
    from facesynth.errors import FacesynthError

    try:
        return json.dumps(obj, indent=1, allow_nan=False, default=_json_default) + "\n"
    except ValueError:
        raise FacesynthError(f"not valid JSON: a non-finite number at {_first_nonfinite(obj) or '?'}") from None


def _first_nonfinite(obj: Any, where: str = "") -> str | None:
    import math

    import numpy as np

    if isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        return where or "top level"
    if isinstance(obj, np.ndarray) and obj.dtype.kind == "f" and not np.isfinite(obj).all():
        return where or "top level"
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, (list, tuple)):
        items = enumerate(obj)
    else:
        return None
    for k, v in items:
        got = _first_nonfinite(v, f"{where}.{k}" if where else str(k))
        if got:
            return got
    return None


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


class Terminated(SystemExit):
    """Raised in the main thread by SIGTERM once :func:`install_sigterm_handler` ran, so that
    ``finally`` blocks and :func:`atomic_path` clean up; exit status 143 (128 + 15)."""


def install_sigterm_handler() -> None:
    """Turn SIGTERM into a :class:`Terminated` exception (the CLI's entry points call this)."""
    def handler(signum, frame):
        raise Terminated(128 + signal.SIGTERM)

    with contextlib.suppress(ValueError):  # not the main thread: leave the default
        signal.signal(signal.SIGTERM, handler)
