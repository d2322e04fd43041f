"""Whether this CPU computes a model's int8 appearance basis exactly (torch-free).

ONNX Runtime's ``MatMulInteger`` (u8 x s8) is exact on x86 with VNNI and on ARM, but on x86
without VNNI it adds pairs of products in a saturating int16 (``vpmaddubsw``): weight codes
beyond :data:`facesynth.contract.CODE_LEVELS` then give wrong textures without any error.
Files written since the 7-bit codes record their range (``appearance_code_levels``); int8
files without it hold 8-bit codes (:data:`facesynth.contract.LEGACY_CODE_LEVELS`).

:func:`check_int8_basis` is what :class:`facesynth.runtime.Renderer` calls on loading: a
file whose codes can saturate is refused on a CPU that saturates and warned about on every
other CPU (the file will render wrong on some machines it is copied to).
"""

from __future__ import annotations

import functools
import logging
import platform

from facesynth.contract import CODE_LEVELS, CODE_LEVELS_KEY, INT16_MAX, LEGACY_CODE_LEVELS, pair_sum_bound
from facesynth.errors import FacesynthError

log = logging.getLogger(__name__)

X86 = ("x86_64", "amd64", "i386", "i686", "x86")
VNNI_FLAGS = ("avx512_vnni", "avx_vnni")  # /proc/cpuinfo names of the two VNNI extensions


def code_levels(metadata: dict) -> int | None:
    """The int8 weight-code range of a synthesis file's appearance basis, or None (float32
    basis, or no global appearance basis)."""
    if metadata.get("appearance_basis") != "int8":
        return None
    value = metadata.get(CODE_LEVELS_KEY, LEGACY_CODE_LEVELS)
    try:
        return int(value)
    except (TypeError, ValueError):
        return LEGACY_CODE_LEVELS  # unreadable: assume the worst


def codes_can_saturate(levels: int | None) -> bool:
    """True when weight codes in [-levels, levels] overflow the int16 pair sums of x86 without VNNI."""
    return levels is not None and pair_sum_bound(levels) > INT16_MAX


def cpu_flags(cpuinfo: str) -> set[str]:
    """The feature flags of the first processor in /proc/cpuinfo text."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return set(value.split())
    return set()


@functools.cache
def cpu_int8_saturates() -> bool | None:
    """Whether ONNX Runtime's u8 x s8 kernel saturates on this CPU: True on x86 without VNNI,
    False with VNNI and on non-x86 CPUs, None when an x86 CPU's flags cannot be read."""
    if platform.machine().lower() not in X86:
        return False
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            flags = cpu_flags(f.read())
    except OSError:
        return None
    if not flags:
        return None
    return not any(f in flags for f in VNNI_FLAGS)


def check_int8_basis(metadata: dict, where: str) -> None:
    """Refuse (FacesynthError) a file whose int8 codes can saturate when this CPU saturates;
    log a warning about it on any other CPU. Files with safe codes, or a float32 basis, pass."""
    levels = code_levels(metadata)
    if not codes_can_saturate(levels):
        return
    run = metadata.get("run")
    redo = f"facesynth export {run if run else 'RUN'} --out {where}"
    what = (f"{where}: its int8 appearance basis has 8-bit codes (up to +-{levels}), which ONNX Runtime computes wrong "
            f"on x86 CPUs without VNNI; re-export it with this version ({redo}; 7-bit codes, up to +-{CODE_LEVELS})")
    if cpu_int8_saturates():
        raise FacesynthError(f"{what}: this CPU has no VNNI, so its renders would be wrong")
    log.warning("%s: it renders right on this CPU, not on every CPU", what)
