"""Which videos a batch runs on, and the subject name (output folder) of each."""

from __future__ import annotations

import glob
import os
import re
from pathlib import Path

from facesynth.errors import FacesynthError

#: Files a folder search picks up (an explicit glob or file takes any suffix).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")


def find_videos(spec: str | os.PathLike) -> list[Path]:
    """The videos ``spec`` names, sorted, each once (by resolved path).

    ``spec`` is a folder (searched recursively for :data:`VIDEO_SUFFIXES`), a glob pattern
    (``**`` allowed; every matching file is taken) or one video file.
    """
    spec = str(spec)
    p = Path(spec)
    if p.is_dir():
        found = [f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in VIDEO_SUFFIXES]
        where = f"{spec}: no video files in this folder (looked for {', '.join(VIDEO_SUFFIXES)})"
    elif p.is_file():
        found, where = [p], ""
    elif glob.has_magic(spec):
        found = [Path(f) for f in glob.glob(spec, recursive=True) if Path(f).is_file()]
        where = f"{spec}: the pattern matches no file"
    else:
        raise FacesynthError(f"{spec}: no such folder or file, and not a glob pattern")
    unique = {f.resolve(): f for f in sorted(found)}
    if not unique:
        raise FacesynthError(where)
    return sorted(unique.values())


def _clean(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "subject"


def subject_names(videos: list[Path]) -> list[str]:
    """One folder name per video, unique and filesystem-safe.

    Per video, the first of these that no other video shares: the file stem
    (``clips/anna.mp4`` -> ``anna``), the parent folder's name (``faces/bob/video.mp4``
    -> ``bob``), both (``bob_video``), the path below the videos' common folder joined
    with ``_``; a numbered suffix settles what is still equal.
    """
    paths = [Path(os.path.abspath(v)) for v in videos]
    if not paths:
        return []
    root = Path(os.path.commonpath([str(p.parent) for p in paths]))
    candidates = (
        lambda p: p.stem,
        lambda p: p.parent.name,
        lambda p: f"{p.parent.name}_{p.stem}",
        lambda p: "_".join(p.relative_to(root).with_suffix("").parts),
    )
    names = []
    for p in paths:
        for make in candidates:
            name = _clean(make(p))
            if sum(_clean(make(q)) == name for q in paths) == 1:
                break
        names.append(name)
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # equal across candidate kinds, or after _clean
        seen[n] = seen.get(n, 0) + 1
        if seen[n] > 1:
            names[i] = f"{n}-{seen[n]}"
    return names
