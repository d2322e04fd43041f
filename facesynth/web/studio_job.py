"""The studio's training job, in a process of its own (so that cancelling it is terminating it):
the page's recorded frames (JPEG) -> one video -> ``facesynth ingest --landmarker mediapipe --copy`` ->
``facesynth train data=video`` (the default configuration) -> ``facesynth export --talking-head``,
each by the function its command calls, all inside one work folder (made by the server inside
the library; renamed to the avatar's name by the server once the avatar is exported). The avatar
is exported as soon as the training has saved its model, before the run's evaluation and
report: the page drives it while they are written (the run folder ends the same as the CLI's).

    python -m facesynth.web.studio_job '{"work": DIR, "overrides": [...], "min_frames": N, "min_face": F}'

Progress goes to the server as JSON lines on stdout, each after :data:`MARK`: ``{"stage",
"fraction"}`` while a stage runs (the ``[facesynth]`` lines the commands print: their progress
bars' ``n/total`` and their finished-stage lines), ``{"live": summary}`` once the avatar is
exported, ``{"done": summary}`` once the report is written, or ``{"error": one line}``. A
process of its own rather than a ``multiprocessing`` child: it does not import the server's
``__main__`` again, whichever way the server was started.
"""

from __future__ import annotations

import io
import json
import os
import re
import sys
import time
from pathlib import Path

# The stages before the avatar goes live, in order, each with its wall-clock seconds in a
# default-config run of a 40 s recording (625 frames kept) on this 2-core host, shared (load
# average 1-3): ``bench/web/studio.py`` (its ``job_s``), docs/studio.md. Only their ratios
# matter: the percent shown is the share of this total done, and the time left is what remains
# of it at the speed seen.
STAGES = (("decode", 1.6), ("ingest", 4.1), ("face model", 10.0), ("SADM fit", 22.3), ("export", 13.0))
# then, with the avatar live, the run's evaluation and report (run_training's remaining stages)
REPORT_STAGES = ("evaluation", "talking head", "report")
VIDEO = "recording.avi"  # the frames, in order: Motion JPEG, quality 95 (OpenCV writes it everywhere)
UPLOAD = "upload.bin"  # the page's frames as received
FPS = 30.0
MARK = "@@facesynth-studio "  # starts each of the job's lines for the server (other output is ignored)
BAR = re.compile(r": (\d+)/(\d+) ")  # a progress bar's line (facesynth.progress.bar)


class _Lines(io.TextIOBase):
    """stderr of the job: each ``[facesynth]`` line the commands print, to ``on_line``."""

    def __init__(self, on_line):
        self.on_line, self.buf = on_line, ""

    def write(self, s: str) -> int:
        self.buf += s
        while "\n" in self.buf:
            line, self.buf = self.buf.split("\n", 1)
            self.on_line(line.strip())
        return len(s)


def decode_upload(upload: Path, out: Path, min_frames: int) -> dict:
    """The page's upload (each frame a 4-byte big-endian length, then its JPEG) -> one video
    ``out`` of the frames in order (Motion JPEG); FacesynthError for a body that is not such
    frames, a frame that does not decode, or a recording shorter than ``min_frames`` frames."""
    import cv2
    import numpy as np

    from facesynth.errors import FacesynthError

    writer, n, size = None, 0, None
    try:
        with open(upload, "rb") as f:
            while head := f.read(4):
                length = int.from_bytes(head, "big")
                data = f.read(length) if len(head) == 4 else b""
                bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if len(data) == length > 0 else None
                if bgr is None:
                    raise FacesynthError(f"the recording cannot be decoded (frame {n + 1} is not a JPEG image)")
                if writer is None:
                    size = (bgr.shape[1], bgr.shape[0])
                    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), FPS, size)
                    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
                if (bgr.shape[1], bgr.shape[0]) != size:
                    raise FacesynthError(f"the recording cannot be decoded (frame {n + 1} is {bgr.shape[1]}x{bgr.shape[0]}, "
                                         f"the first {size[0]}x{size[1]})")
                writer.write(bgr)
                n += 1
    finally:
        if writer is not None:
            writer.release()
    if n < min_frames:
        raise FacesynthError(f"the recording is too short: {n} frames, at least {min_frames} are needed")
    return {"frames": n}


def estimate(stage: str, fraction: float, elapsed_s: float, stages=STAGES) -> tuple[float, float]:
    """(percent done, seconds left) of the job before the avatar goes live, with ``stage`` (one of
    ``stages``' names) ``fraction`` done after ``elapsed_s`` seconds: the stages' measured seconds
    give the percent; the time left is the seconds the stages still need at the speed seen so
    far (the job's elapsed time over the measured seconds done), the measured seconds themselves
    before 3 % is done (too little to judge the speed)."""
    names = [n for n, _ in stages]
    seconds = dict(stages)
    total = sum(seconds.values())
    done = sum(seconds[n] for n in names[:names.index(stage)]) + seconds[stage] * max(0.0, min(1.0, fraction))
    p = done / total
    left = total - done
    return 100 * p, (left * elapsed_s / done if p >= 0.03 else left)


# a finished stage's line (``[facesynth] NAME...in X s``) -> the stage that starts then, and its fraction
NEXT = (("ingest", "face model", 0.0), ("face model", "SADM fit", 0.0), ("SADM fit", "export", 0.0),
        ("ONNX export", "export", 0.7), ("evaluation", "talking head", 0.0), ("talking head", "report", 0.0))


def run_job(work: str, overrides: list[str], min_frames: int, min_face: float, queue) -> None:
    """The job's process: everything inside ``work`` (its working folder, so that the server can
    rename it to the avatar's name once the avatar is live, while the report is written);
    reports on ``queue``: stages until ``{"live": summary}`` (the avatar exported), then the
    report's stages until ``{"done": summary}``, or ``{"error": one line}``."""
    os.chdir(work)  # relative paths from here on (and in the run's config): the folder can be renamed
    work_dir = Path(".")
    current = {"stage": "decode", "t": time.perf_counter(), "cpu": time.process_time()}
    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}  # each stage's CPU seconds (every thread of the job): the host is shared

    def close_stage() -> None:
        now, now_cpu = time.perf_counter(), time.process_time()
        timings[current["stage"]] = timings.get(current["stage"], 0.0) + now - current["t"]
        cpu[current["stage"]] = cpu.get(current["stage"], 0.0) + now_cpu - current["cpu"]
        current.update(t=now, cpu=now_cpu)

    names = [n for n, _ in STAGES] + list(REPORT_STAGES)

    def report(stage: str, fraction: float) -> None:
        if stage != current["stage"]:  # each stage's seconds, from its first report to the next stage's
            close_stage()
            current["stage"] = stage
        queue.put({"stage": stage, "fraction": max(0.0, min(1.0, fraction))})

    def on_line(line: str) -> None:
        if not line.startswith("[facesynth]"):
            return
        text = line[len("[facesynth]"):].strip()
        if re.search(r" in \d+(\.\d+)? s$", text):
            for name, nxt, fraction in NEXT:
                if text.startswith(name):
                    report(nxt, fraction)
                    return
        m = BAR.search(text)
        if m and int(m.group(2)) > 0:
            report(current["stage"], int(m.group(1)) / int(m.group(2)))
        elif any(text.startswith(n) for n in names):  # a stage's first line
            report(next(n for n in names if text.startswith(n)), 0.0)

    sys.stderr = _Lines(on_line)
    from facesynth.errors import FacesynthError
    from facesynth.io import install_sigterm_handler, is_disk_full

    install_sigterm_handler()  # SIGTERM (cancel) unwinds: the commands remove their temporary files
    summary: dict = {}
    try:
        report("decode", 0.0)
        rec = decode_upload(work_dir / UPLOAD, work_dir / VIDEO, min_frames)
        (work_dir / UPLOAD).unlink()

        report("ingest", 0.0)
        from facesynth.data.ingest import ingest_video

        seq = ingest_video(work_dir / VIDEO, work_dir / "ingest", landmarker="mediapipe", copy=True, progress=True)
        (work_dir / VIDEO).unlink()  # the ingest folder holds its copy
        rate = seq.meta["stats"]["detection_rate"]
        if rate < min_face:
            raise FacesynthError(f"no face in most frames: the tracker found one in {rate:.0%} of "
                                 f"{rec['frames']} frames (at least {min_face:.0%} are needed): face the camera, in good light")

        report("face model", 0.0)
        from facesynth.onnx.export import export_talking_head_model
        from facesynth.runs.config import compose_config
        from facesynth.runs.training import run_training

        def go_live() -> None:  # the SADM is saved: export the avatar; the page drives it while the report is made
            report("export", 0.0)
            export = export_talking_head_model("run", "avatar.onnx")
            report("evaluation", 0.0)
            summary.update({"frames": rec["frames"], "detection_rate": rate, "overrides": list(overrides),
                            "seconds": {k: round(v, 2) for k, v in timings.items()},
                            "cpu_seconds": {k: round(v, 2) for k, v in cpu.items()}, "onnx_bytes": export["bytes"]})
            Path("studio.json").write_text(json.dumps(summary, indent=1))
            queue.put({"live": summary})

        cfg = compose_config(["data=video", "data.path=ingest", *overrides])
        metrics = run_training(cfg, "run", on_fitted=go_live)
        close_stage()
        summary.update({"seconds": {k: round(v, 2) for k, v in timings.items()},
                        "cpu_seconds": {k: round(v, 2) for k, v in cpu.items()}, "psnr_ref": metrics.get("psnr_ref")})
        Path("studio.json").write_text(json.dumps(summary, indent=1))
        queue.put({"done": summary})
    except FacesynthError as exc:
        queue.put({"error": str(exc)})
    except OSError as exc:
        if not is_disk_full(exc):
            queue.put({"error": f"{type(exc).__name__}: {exc}"})
        else:
            queue.put({"error": "the disk is full: free some space and train again"})
    except Exception as exc:  # noqa: BLE001 - any failure of the training is one line in the page
        queue.put({"error": f"training failed in {current['stage']}: {type(exc).__name__}: {exc}"})


class _Messages:
    """The server's end: each message one JSON line on the process's stdout, after MARK."""

    def __init__(self, fd: int):
        self.fd = fd

    def put(self, msg: dict) -> None:
        os.write(self.fd, (MARK + json.dumps(msg) + "\n").encode())


def one_thread() -> None:
    """The job's numerical libraries on one thread each: torch's, and numpy's BLAS (threadpoolctl). The
    page tracks the camera on a core meanwhile, and two BLAS threads spinning for a busy core took the
    SADM fit from 19 to 116 s; on one it takes 20-23 s either way (docs/studio.md: threads)."""
    import numpy  # noqa: F401  (loaded first: threadpoolctl limits only the BLAS already loaded)
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(1)


def main(argv: list[str] | None = None) -> None:
    args = json.loads((argv if argv is not None else sys.argv[1:])[0])
    out = _Messages(os.dup(sys.stdout.fileno()))
    sys.stdout = sys.__stderr__  # anything a library prints goes elsewhere than the messages
    one_thread()
    run_job(args["work"], args["overrides"], args["min_frames"], args["min_face"], out)


if __name__ == "__main__":
    main()
