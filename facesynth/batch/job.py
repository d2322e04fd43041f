"""One subject's job: ingest -> train + evaluate -> export, each stage skipped when its
outputs are complete and valid (:mod:`facesynth.batch.state`), redone otherwise.

The job never raises for a subject's own failure (no face, too short, a stage error): it
returns the subject's row with ``status='failed'`` and the reason, so the others go on.
Everything it logs or prints goes to ``DIR/<subject>/subject.log``.
"""

from __future__ import annotations

import contextlib
import logging
import resource
import shutil
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from facesynth.batch import state
from facesynth.errors import FacesynthError
from facesynth.io import write_json

#: Stages in order; evaluation is part of training (run_training evaluates the held-out split).
STAGES = ("ingest", "train", "export")
TIME_KEYS = ("ingest_s", "train_s", "evaluate_s", "export_s")

Report = Callable[[str, str], None]


@dataclass(frozen=True)
class SubjectJob:
    """What to do for one subject (plain data: it travels to Ray workers).

    ``config`` is the composed training config as a container, with ``data.path`` already
    pointing at ``out``; ``export`` holds ``opset``, ``components``, ``basis``.
    ``threads``: torch / OpenCV threads for this job (``None``: leave the process's setting).
    """

    name: str
    video: str
    out: str
    config: dict
    export: dict
    every: int = 1
    max_frames: int | None = None
    landmarker: str = "dlib"
    min_frames: int = 30
    threads: int | None = None


@contextlib.contextmanager
def subject_log(path: Path):
    """Route logging, warnings, stdout and stderr to ``path`` (appended) for the block."""
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", buffering=1, encoding="utf-8") as f:
        handler = logging.StreamHandler(f)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.handlers, root.level = [handler], logging.INFO
        logging.captureWarnings(True)
        try:
            with contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
                yield logging.getLogger("facesynth.batch")
        finally:
            logging.captureWarnings(False)
            root.handlers, root.level = saved


def pin_threads(n: int) -> None:
    """torch and OpenCV use ``n`` threads (the job's CPU share)."""
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)


def _ingest(job: SubjectJob, out: Path) -> None:
    from facesynth.data.ingest import ingest_video

    ingest_video(job.video, out / state.DATA_DIR, every=job.every, max_frames=job.max_frames)  # replaces data/ whole


def _train(job: SubjectJob, out: Path) -> dict:
    from omegaconf import OmegaConf

    from facesynth.runs.training import run_training

    partial, final = out / (state.RUN_DIR + ".partial"), out / state.RUN_DIR
    shutil.rmtree(partial, ignore_errors=True)
    metrics = run_training(OmegaConf.create(job.config), partial)
    shutil.rmtree(final, ignore_errors=True)
    partial.rename(final)
    return metrics


def _export(job: SubjectJob, out: Path) -> dict:
    from facesynth.onnx.export import export_model

    (out / state.EXPORT_FILE).unlink(missing_ok=True)
    opts = job.export
    summary = export_model(out / state.RUN_DIR, out / state.MODEL_FILE, opts["opset"], opts["components"], None,
                           None, True, opts["basis"])
    write_json(out / state.EXPORT_FILE, {"options": opts, "summary": summary})
    return summary


def _previous_times(out: Path) -> dict:
    import json

    try:
        return json.loads((out / state.RESULT_FILE).read_text()).get("times", {})
    except (OSError, ValueError):
        return {}


def _figures(out: Path) -> dict:
    """The row's figures, read back from the subject's outputs (whatever exists)."""
    import json

    import numpy as np

    fig: dict = {}
    if (out / state.DATA_DIR / "meta.json").is_file():
        lm = np.load(out / state.DATA_DIR / "landmarks.npy", mmap_mode="r")
        fig["frames"] = int(lm.shape[0])
        fig["face_frames"] = int(np.isfinite(np.asarray(lm[:, 0, 0])).sum())
    mpath = out / state.RUN_DIR / "metrics.json"
    if mpath.is_file():
        m = json.loads(mpath.read_text())
        fig.update(regressor=m["regressor"], train_frames=m["train_frames"], test_frames=m["test_frames"],
                   psnr_sadm=m["psnr_ref"]["sadm"].get("0"), psnr_mean_texture=m["psnr_ref"]["mean_texture"].get("0"),
                   psnr_oracle=m["psnr_ref"]["oracle"].get("0"))
    epath = out / state.EXPORT_FILE
    if epath.is_file() and (out / state.MODEL_FILE).is_file():
        fig["export_bytes"] = (out / state.MODEL_FILE).stat().st_size
    return fig


def _run_stages(job: SubjectJob, out: Path, log: logging.Logger, enter: Callable[[str], None], times: dict) -> list[str]:
    """Check and (re)do each stage (``enter(stage)`` before each one that runs); returns
    the stages that ran. Raises on failure."""
    from facesynth.data import load_sequence

    ran: list[str] = []
    video = Path(job.video)
    ok, why = state.ingest_state(out / state.DATA_DIR, video, job.every, job.max_frames, job.landmarker)
    if not ok:
        log.info("ingest: %s -> ingesting %s", why, video)
        enter("ingest")
        t0 = time.perf_counter()
        _ingest(job, out)
        times["ingest_s"] = time.perf_counter() - t0
        ran.append("ingest")
    enter("check")
    seq = load_sequence(out / state.DATA_DIR)
    if len(seq) < job.min_frames:
        raise FacesynthError(f"too short: {len(seq)} frames with a face, fewer than the {job.min_frames} needed (--min-frames)")

    ok, why = (False, "ingest was redone") if ran else state.train_state(out / state.RUN_DIR, job.config, seq.fingerprint)
    if not ok:
        log.info("train: %s -> training", why)
        enter("train")
        t0 = time.perf_counter()
        metrics = _train(job, out)
        wall = time.perf_counter() - t0
        times["evaluate_s"] = metrics["timings_s"]["evaluate"]
        times["train_s"] = wall - times["evaluate_s"]
        ran.append("train")
    regressor = job.config["regressor"]["name"]
    ok, why = (False, "training was redone") if ran else state.export_state(
        out / state.MODEL_FILE, out / state.EXPORT_FILE, job.export, seq.fingerprint, regressor)
    if not ok:
        log.info("export: %s -> exporting", why)
        enter("export")
        t0 = time.perf_counter()
        _export(job, out)
        times["export_s"] = time.perf_counter() - t0
        ran.append("export")
    return ran


def run_subject(job: SubjectJob, report: Report | None = None) -> dict:
    """Run (or resume) one subject; returns its summary row (also ``result.json``)."""
    report = report or (lambda name, stage: None)
    out = Path(job.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    row: dict = {"subject": job.name, "status": "failed", "ran": "", "reason": "", "video": job.video,
                 "started": time.time()}
    times: dict = {}  # of the stages run now; a complete subject keeps those of earlier runs
    report(job.name, "check")
    with subject_log(out / state.LOG_FILE) as log:
        log.info("subject %s: video %s", job.name, job.video)
        if job.threads:
            pin_threads(job.threads)
        current = ["check"]

        def enter(stage: str) -> None:
            current[0] = stage
            report(job.name, stage)

        try:
            ran = _run_stages(job, out, log, enter, times)
            row.update(status="ok" if ran else "skipped", ran="+".join(ran))
            log.info("subject %s: %s", job.name, f"ran {row['ran']}" if ran else "complete, nothing to do")
        except Exception as exc:  # noqa: BLE001 - one subject's failure must not stop the batch
            msg = str(exc) if isinstance(exc, FacesynthError) else f"{type(exc).__name__}: {exc}"
            row["reason"] = msg if current[0] == "check" else f"{current[0]}: {msg}"
            log.error("subject %s failed: %s", job.name, row["reason"])
            if not isinstance(exc, FacesynthError):
                log.error("%s", traceback.format_exc())
        figures = _figures(out)
        if row["status"] == "failed":  # older outputs of a failed subject are not its figures
            figures = {k: v for k, v in figures.items() if k in ("frames", "face_frames")}
        row.update(figures)
        previous = {k: v for k, v in _previous_times(out).items() if k in TIME_KEYS}
        row["times"] = times if row["status"] == "failed" else {**previous, **times}
        row["wall_s"] = time.perf_counter() - t_start
        row["finished"] = time.time()
        # the process's peak so far: this subject's peak when the process ran only it (a fresh worker)
        row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        write_json(out / state.RESULT_FILE, row)
    report(job.name, row["status"])
    return row
