"""Locating the real evaluation data that lives beside the project (``../shared/data``).

The data is never copied into the repository; tests and benchmarks that need it call
:func:`shared_data_dir` and skip when it returns ``None``.
"""

from __future__ import annotations

import os
from pathlib import Path


def shared_data_dir() -> Path | None:
    """The ``shared/data`` folder, or ``None`` when it is absent.

    Looks at ``$FACESYNTH_SHARED_DATA`` first, then for ``../shared/data`` beside the
    current directory and beside the source tree of this package.
    """
    env = os.environ.get("FACESYNTH_SHARED_DATA")
    candidates = [Path(env)] if env else []
    here = Path(__file__).resolve()
    for base in (Path.cwd().resolve(), here.parents[2]):
        candidates += [base.parent / "shared" / "data", base / "shared" / "data"]
    for c in candidates:
        if (c / "faces").is_dir() or (c / "mesh").is_dir():
            return c
    return None


def shared_clip(name: str) -> Path | None:
    """``shared/data/faces/<name>`` if present."""
    root = shared_data_dir()
    if root is None or not (root / "faces" / name / "landmarks.npy").is_file():
        return None
    return root / "faces" / name


def shared_mesh_dir() -> Path | None:
    """``shared/data/mesh`` if present."""
    root = shared_data_dir()
    return root / "mesh" if root is not None and (root / "mesh").is_dir() else None
