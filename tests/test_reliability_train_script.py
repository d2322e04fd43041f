"""``train.py`` as a user meets it: a first line at once, each stage once, Ctrl-C is
"interrupted" (exit 130), and one run per folder (a second train.py on a folder in use
refuses, exit 2; a lock left by a dead run is taken over)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from facesynth.runs.lock import LOCK_NAME, lock_run_dir, release_run_dirs

ROOT = Path(__file__).resolve().parents[1]
TINY = ["regressor=linear", "data.n_frames=40", "data.size=128", "eval.frame_level=false", "eval.train_level=false",
        "eval.noise=[0.0]"]


def _train(*args: str, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, str(ROOT / "train.py"), *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


def test_first_line_at_once_and_each_stage_once(tmp_path):
    p = _train(*TINY, f"hydra.run.dir={tmp_path / 'run'}")
    first = p.stderr.readline()  # before torch is imported
    out, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    assert first.startswith("[facesynth] train.py: starting")
    text = out + err
    assert text.count("face model") == 1 and "[INFO]" not in text  # Hydra's info lines go to train.log only
    assert "[facesynth] face model: 30 training frames" in err
    assert "face model:" in (tmp_path / "run" / "train.log").read_text()
    assert not (tmp_path / "run" / LOCK_NAME).exists()  # released at the end
    q = _train(*TINY, "quiet=true", f"hydra.run.dir={tmp_path / 'quiet'}")
    out, err = q.communicate(timeout=300)
    assert q.returncode == 0 and "[facesynth]" not in err, err[-2000:]


def test_ctrl_c_is_interrupted_exit_130(tmp_path):
    run = tmp_path / "run"
    # an MLP that would train for ever: Ctrl-C lands while it fits
    # a terminal's Ctrl-C: SIGINT at its default in the child, whatever this process inherited (a shell's
    # background job, as CI may run the suite, ignores SIGINT, and Python keeps an ignored SIGINT ignored)
    p = _train("regressor=mlp", "regressor.max_epochs=100000000", "regressor.patience=100000000", "data.n_frames=40",
               "data.size=128", f"hydra.run.dir={run}",
               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in p.stderr:
        if line.startswith("[facesynth] face model:"):  # the run has started: the SADM fit is next
            break
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 130, err[-2000:]
    assert err.strip().splitlines() == ["interrupted"] and "Traceback" not in err
    names = sorted(q.name for q in run.iterdir())
    assert names == [".hydra", "config.yaml", "train.log"]  # nothing half written, no temporaries, no lock


def test_a_run_folder_in_use_is_refused(tmp_path):
    run = tmp_path / "run"
    lock_run_dir(run)  # this process holds the folder, as a running train.py does
    try:
        p = _train(*TINY, f"hydra.run.dir={run}")
        out, err = p.communicate(timeout=300)
    finally:
        release_run_dirs()
    assert p.returncode == 2, err[-2000:]
    lines = [ln for ln in err.splitlines() if not ln.startswith("[facesynth]")]
    assert lines == [f"error: {run}: run folder in use by another train.py (pid {os.getpid()}); wait for it to end "
                     "or choose another hydra.run.dir"]
    assert not run.exists()  # nothing written (our own empty folder was removed on release)


def test_a_lock_left_by_a_dead_run_is_taken_over(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (run / LOCK_NAME).write_text(f"{dead.pid}\n")  # a SIGKILLed run's file: no process holds its lock
    p = _train(*TINY, f"hydra.run.dir={run}")
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    assert (run / "metrics.json").is_file() and not (run / LOCK_NAME).exists()
