"""Running subject jobs: Ray tasks (a local runtime or a cluster), or a plain loop.

Ray does all the scheduling: each subject is one task that requests ``cpus`` CPUs and an
estimate of the memory it needs, so Ray never runs more subjects at once than the
machine (or cluster) holds. The job pins torch and OpenCV to its CPU share. Progress
events travel from the workers to the driver through a small actor.
Without Ray (or with ``sequential=True``) the jobs run one after another in this process.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Sequence

from facesynth.batch.job import SubjectJob, run_subject
from facesynth.errors import FacesynthError

log = logging.getLogger(__name__)

# Memory a subject job asks Ray for: the least-squares line through the peak resident memory
# of one subject job at 60 / 300 / 1008 frames (default config with frame-level evaluation,
# 480x480 video; ``bench/train/batch.py --memory``, figures in docs/scale.md) plus a Ray
# worker's own overhead, rounded up by about 20 %. Ray then runs at most (node memory /
# request) subjects at once on a node.
MEMORY_BASE_MB = 600
MEMORY_PER_FRAME_MB = 2.0

FINAL_STATES = ("ok", "skipped", "failed")


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def video_frames(path: str, every: int, max_frames: int | None) -> int:
    """Frames a job will ingest (from the video header; 0 when the header has no count)."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) if cap.isOpened() else 0
    cap.release()
    if max_frames:
        n = min(n, max_frames) if n else max_frames
    return math.ceil(n / every)


def memory_request(frames: int) -> int:
    """Bytes of memory a subject job with ``frames`` frames asks for (see MEMORY_* above)."""
    return int((MEMORY_BASE_MB + MEMORY_PER_FRAME_MB * frames) * 2**20)


class Progress:
    """One bar over subjects; its postfix shows the stage of each running subject."""

    def __init__(self, total: int, enabled: bool = True):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=total, unit="subject", desc="batch", disable=not enabled, dynamic_ncols=True, leave=True)
        self.running: dict[str, str] = {}

    def __call__(self, name: str, stage: str) -> None:
        if stage in FINAL_STATES:
            self.running.pop(name, None)
            self.bar.update(1)
        else:
            self.running[name] = stage
        self.bar.set_postfix_str(" ".join(f"{n}:{s}" for n, s in self.running.items()) or "-", refresh=True)

    def close(self) -> None:
        self.bar.close()


def run_sequential(jobs: Sequence[SubjectJob], on_event: Callable[[str, str], None]) -> list[dict]:
    """The fallback without Ray: one subject after another, in this process."""
    return [run_subject(job, on_event) for job in jobs]


class _Events:
    """Progress events from the tasks, held for the driver (a Ray actor).

    Tasks push without waiting for the reply: a task blocked in ``ray.get`` lends its CPU
    back to Ray, which would then start another subject on it (oversubscription)."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str]] = []

    def push(self, name: str, stage: str) -> None:
        self.items.append((name, stage))

    def drain(self) -> list[tuple[str, str]]:
        items, self.items = self.items, []
        return items


def _ray_task(job: SubjectJob, events) -> dict:
    return run_subject(job, lambda name, stage: events.push.remote(name, stage))


def _failed_row(job: SubjectJob, reason: str) -> dict:
    return {"subject": job.name, "status": "failed", "ran": "", "reason": reason, "video": job.video, "times": {}}


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Fail fast when nothing listens at a HOST:PORT or ray://HOST:PORT address (ray.init
    would otherwise retry for minutes). 'auto' and other forms are left to Ray."""
    import socket

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as exc:
        raise FacesynthError(f"Ray cluster at {address}: nothing answers there ({exc.strerror or exc})") from None


def start_ray(address: str | None, num_cpus: int | None) -> tuple[bool, str]:
    """Connect to ``address`` (or ``$RAY_ADDRESS``), else start a local runtime with
    ``num_cpus``; returns (started here, description). An already initialised Ray is used as is."""
    import ray

    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        _check_reachable(address)
    if ray.is_initialized():
        return False, f"Ray already running in this process ({ray.cluster_resources().get('CPU', 0):g} CPUs)"
    opts = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    if address:
        try:
            ray.init(address=address, **opts)
        except (ConnectionError, RuntimeError, ray.exceptions.RayError) as exc:
            lines = [ln for ln in str(exc).splitlines() if ln.strip()]
            raise FacesynthError(
                f"Ray cluster at {address}: could not connect ({(lines[-1] if lines else type(exc).__name__)[:200]}); "
                "a cluster with token authentication needs RAY_AUTH_MODE=token and its token "
                "(~/.ray/auth_token or RAY_AUTH_TOKEN), see docs/scale.md") from None
        where = f"Ray cluster at {address}"
    else:
        ray.init(num_cpus=num_cpus, **opts)
        where = "local Ray runtime"
    return True, f"{where} ({ray.cluster_resources().get('CPU', 0):g} CPUs)"


def _node_memory_cap() -> int | None:
    """The largest node's memory resource (a request above it would never be scheduled)."""
    import ray

    mem = [n.get("Resources", {}).get("memory", 0) for n in ray.nodes() if n.get("Alive")]
    return int(max(mem)) if mem and max(mem) > 0 else None


def run_ray(jobs: Sequence[SubjectJob], on_event: Callable[[str, str], None], *, cpus: float,
            memory: Sequence[int], retries: int) -> list[dict]:
    """Run the jobs as Ray tasks (Ray must be initialised, see :func:`start_ray`).

    ``memory[i]``: bytes requested for ``jobs[i]``, capped at the largest node's memory.
    A worker that dies (out of memory, node lost) is retried ``retries`` times by Ray; after
    that its subject fails with Ray's reason. Returns rows in the order of ``jobs``.
    """
    import ray

    events = ray.remote(num_cpus=0)(_Events).remote()
    task = ray.remote(_ray_task)
    cap = _node_memory_cap()
    refs = {}
    for job, mem in zip(jobs, memory, strict=True):
        mem = min(mem, cap) if cap else mem
        refs[task.options(num_cpus=cpus, memory=mem, max_retries=retries).remote(job, events)] = job

    def drain() -> None:
        for name, stage in ray.get(events.drain.remote()):
            on_event(name, stage)

    rows: dict[str, dict] = {}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            drain()
            for ref in done:
                job = refs[ref]
                try:
                    rows[job.name] = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                    rows[job.name] = _failed_row(job, f"ray: {type(exc).__name__}: {first[:300]}")
                    on_event(job.name, "failed")
        drain()
    finally:
        for ref in pending:  # interrupted: do not leave tasks running
            ray.cancel(ref, force=True)
        ray.kill(events)
    return [rows[j.name] for j in jobs]
