"""What every bench shares: the host it ran on, the machine's load around the run, one JSON
line, and speed as a same-run ratio (timings on a shared machine drift, so two things are
timed interleaved in one run and compared as a ratio, never against an earlier run's figure).

    out = {"bench": "x", **host()}            # CPU model and flags, cores
    with load() as around:                    # load average at start and end
        ... measure ...
    emit({**out, "load": around})             # one JSON line on stdout
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import statistics
import time
from pathlib import Path

FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")  # what changes ONNX Runtime's kernels


def cpu_flags() -> list[str]:
    """The CPU flags of :data:`FLAGS` this host has ([] where /proc/cpuinfo cannot be read)."""
    from facesynth.runtime.cpu import cpu_flags as parse

    try:
        flags = parse(Path("/proc/cpuinfo").read_text())
    except OSError:
        return []
    return sorted(f for f in flags if f in FLAGS)


def host() -> dict:
    """The host as benches record it: CPU model, its relevant flags, cores."""
    model = platform.processor()
    with contextlib.suppress(OSError):
        model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith("model name")), model)
    return {"host": {"cpu": model, "cpu_flags": cpu_flags(), "cores": os.cpu_count()}}


def load_average() -> float:
    """The 1-minute load average now (other processes compete for the cores)."""
    return round(os.getloadavg()[0], 2)


def load_averages() -> list[float]:
    """The 1-, 5- and 15-minute load averages now."""
    return [round(v, 2) for v in os.getloadavg()]


@contextlib.contextmanager
def load():
    """A dict ``{"start": ..., "end": ...}`` of the 1-minute load average around the block."""
    around = {"start": load_average()}
    try:
        yield around
    finally:
        around["end"] = load_average()


def emit(figures: dict) -> None:
    """``figures`` as the bench's one JSON line on stdout (numpy scalars as numbers), with the
    host and the load average at the end added where the bench has not recorded them."""
    out = figures if "host" in figures else {**figures, **host()}
    if not any("load" in k for k in out):
        out = {**out, "load_average_at_end": load_average()}

    def plain(v):
        return v.item() if hasattr(v, "item") else str(v)

    print(json.dumps(out, default=plain), flush=True)


def ratio(a, b, rounds: int = 10, reps: int = 20) -> dict:
    """Time ``a()`` and ``b()`` interleaved, ``rounds`` rounds of ``reps`` calls each, after one
    warm-up call each; their median seconds per call and the same-run ratio b / a."""
    a(), b()
    times = {"a": [], "b": []}
    for _ in range(rounds):
        for name, fn in (("a", a), ("b", b)):
            t0 = time.perf_counter()
            for _ in range(reps):
                fn()
            times[name].append((time.perf_counter() - t0) / reps)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"a_s": med["a"], "b_s": med["b"], "ratio_b_over_a": med["b"] / med["a"], "rounds": rounds, "reps": reps}


def add_scheme_pairs(parser, dense: str = "the dense scheme") -> None:
    """``--dense RUN ...`` and ``--base RUN ...``: runs of one clip each, in the same clip order."""
    parser.add_argument("--dense", nargs="+", required=True, help=f"run folders of {dense}, one per clip")
    parser.add_argument("--base", nargs="+", required=True, help="run folders of ibug68, in the same clip order")


def scheme_pairs(args):
    """Each (dense run, base run, dense metrics, base metrics) of :func:`add_scheme_pairs`'s
    options; a count that differs or a metrics file that cannot be read is one error line, exit 2."""
    import sys

    from facesynth.errors import FacesynthError
    from facesynth.io import read_json_object

    if len(args.dense) != len(args.base):
        print(f"error: --dense has {len(args.dense)} runs but --base has {len(args.base)}: give one of each per clip",
              file=sys.stderr)
        sys.exit(2)
    for d, b in zip(args.dense, args.base, strict=True):
        try:
            md, mb = (read_json_object(Path(r) / "metrics.json") for r in (d, b))
        except FacesynthError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
        yield d, b, md, mb
