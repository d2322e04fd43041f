"""An ingest folder's ``meta.json``: the fields the loaders read, checked when it is read.

``facesynth ingest`` writes many more fields (statistics, versions); only those that
loading, training and the app act on are checked here, each against its expected type,
so a hand-edited file gives one line naming the file, the field and what was expected
instead of a traceback far away. A field that is absent or ``null`` is not checked (the
loaders fall back: no video, the scheme from the point count, ...).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Callable

from facesynth.errors import FacesynthError
from facesynth.io import read_json_object
from facesynth.landmarks import SCHEMES

META = "meta.json"


def _str(v) -> bool:
    return isinstance(v, str)


def _object(v) -> bool:
    return isinstance(v, dict)


def _number_ge0(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


def _int_ge(lo: int) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _shape(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(_int_ge(0)(d) for d in v) and v[2] == 2


def _scheme(v) -> bool:
    return isinstance(v, str) and v in SCHEMES


FIELDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "name": (_str, "a string"),
    "video": (_object, "an object"),
    "video.file": (_str, "a file name in the folder (a string)"),
    "video.path": (_str, "a path (a string)"),
    "video.fps": (_number_ge0, "a number >= 0 (frames per second; 0: unknown)"),
    "video.width": (_int_ge(1), "an integer >= 1 (pixels)"),
    "video.height": (_int_ge(1), "an integer >= 1 (pixels)"),
    "video.frames": (_int_ge(0), "an integer >= 0"),
    "video.sha256": (_str, "a string"),
    "landmarks": (_object, "an object"),
    "landmarks.file": (_str, "a file name (a string)"),
    "landmarks.shape": (_shape, "[frames, points, 2] (non-negative integers)"),
    "landmarks.scheme": (_scheme, f"one of {', '.join(sorted(SCHEMES))}"),
    "landmarks.sha256": (_str, "a string"),
    "landmarks.every": (_int_ge(1), "an integer >= 1"),
    "landmarks.max_frames": (_int_ge(1), "an integer >= 1 or null"),
}
"""Dotted field -> (check, what is expected)."""


def check_ingest_meta(meta: dict, where: str | os.PathLike) -> dict:
    """``meta`` when every field of :data:`FIELDS` it has is as expected; FacesynthError
    ``WHERE: FIELD must be EXPECTED, got VALUE`` otherwise (fields in the order above, so
    an object is checked before its members)."""
    for name, (ok, expected) in FIELDS.items():
        parent, _, key = name.rpartition(".")
        node = meta.get(parent) if parent else meta
        if not isinstance(node, dict) or node.get(key) is None:
            continue
        value = node[key]
        if not ok(value):
            shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
            raise FacesynthError(f"{where}: {name} must be {expected}, got {shown}")
    return meta


def read_ingest_meta(folder: str | os.PathLike) -> dict:
    """The checked ``meta.json`` of an ingest folder; ``{}`` when the folder has none."""
    path = Path(folder) / META
    return check_ingest_meta(read_json_object(path), path) if path.is_file() else {}
