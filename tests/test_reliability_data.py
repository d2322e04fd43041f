"""Hand-edited or wrong training data through ``train.py``: one line naming the file and the
field, with what was expected, exit 2, no traceback, nothing trained, the data untouched.

meta.json is checked against its fields when read (facesynth.data.meta), the landmarks'
size before the face model (a face spans at least data.sequence.MIN_FACE_PX pixels), the
video an ingest folder names, and the ``data.*`` settings before anything is loaded. A run
refused so leaves no run folder (one it created; an existing folder is kept)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from facesynth.data import load_sequence
from facesynth.data.meta import check_ingest_meta
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clip_arrays():
    seq = make_synthetic_sequence(n_frames=24, size=128, seed=4)
    return seq.load_frames(), seq.landmarks


def _folder(tmp_path: Path, frames, lm) -> Path:
    """An ingest folder as the shared clips are laid out: video.mp4, landmarks.npy, meta.json."""
    d = tmp_path / "clip"
    d.mkdir()
    vw = cv2.VideoWriter(str(d / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (128, 128))
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    vw.release()
    np.save(d / "landmarks.npy", lm)
    meta = {"name": "clip", "video": {"file": "video.mp4", "width": 128, "height": 128, "fps": 25.0,
                                      "frames": len(frames)},
            "landmarks": {"file": "landmarks.npy", "shape": list(lm.shape), "scheme": "ibug68"}}
    (d / "meta.json").write_text(json.dumps(meta))
    return d


def _snapshot(d: Path) -> dict:
    return {p.name: p.read_bytes() for p in d.iterdir()}


def _train(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, str(ROOT / "train.py"), "regressor=linear", "eval.noise=[0.0]",
                           f"hydra.run.dir={tmp_path / 'run'}", *overrides],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def _edit_meta(d: Path, section: str, key: str, value) -> None:
    meta = json.loads((d / "meta.json").read_text())
    meta[section][key] = value
    (d / "meta.json").write_text(json.dumps(meta))


CASES = {
    # name: (how the data is spoiled, the setting overrides, the expected line after "error: ")
    "fps_text": (lambda d: _edit_meta(d, "video", "fps", "twenty-five"), (),
                 "{d}/meta.json: video.fps must be a number >= 0 (frames per second; 0: unknown), got 'twenty-five'"),
    "file_number": (lambda d: _edit_meta(d, "video", "file", 5), (),
                    "{d}/meta.json: video.file must be a file name in the folder (a string), got 5"),
    "scheme_unknown": (lambda d: _edit_meta(d, "landmarks", "scheme", "ibug999"), (),
                       "{d}/meta.json: landmarks.scheme must be one of ibug68, ibug68+iris, mediapipe478, got 'ibug999'"),
    "collapsed": (lambda d: np.save(d / "landmarks.npy", np.full((24, 68, 2), 64.0, np.float32)), (),
                  "{d}/landmarks.npy: landmarks of 24 of 24 rows (first [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]) span 0 px, a "
                  "face needs at least 8 px (landmarks in 0-1 units instead of pixels, or collapsed to one point?)"),
    "unit_coords": (lambda d: np.save(d / "landmarks.npy", np.load(d / "landmarks.npy") / 128), (),
                    "{d}/landmarks.npy: landmarks of 24 of 24 rows (first [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]) span "),
    "no_video": (lambda d: (d / "video.mp4").unlink(), (),
                 "{d}/video.mp4: video not found; training needs the frames of {d}/landmarks.npy"),
    "max_frames_negative": (lambda d: None, ("data.max_frames=-5",),
                            "data.max_frames must be >= 1 (or null: every frame), got -5"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_training_data_is_one_line(clip_arrays, tmp_path, case):
    spoil, overrides, expected = CASES[case]
    d = _folder(tmp_path, *clip_arrays)
    spoil(d)
    before = _snapshot(d)
    r = _train(tmp_path, "data=video", f"data.path={d}", *overrides)
    assert r.returncode == 2, r.stderr[-2000:]
    assert "Traceback" not in r.stderr and "Warning" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if not ln.startswith("[facesynth]")]
    assert len(lines) == 1 and lines[0].startswith("error: " + expected.format(d=d)), lines
    assert _snapshot(d) == before  # the data untouched
    assert not (tmp_path / "run").exists()  # refused before anything was written: no run folder


def test_a_refused_run_keeps_a_folder_it_did_not_create(clip_arrays, tmp_path):
    d = _folder(tmp_path, *clip_arrays)
    (d / "video.mp4").unlink()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    r = _train(tmp_path, "data=video", f"data.path={d}")
    assert r.returncode == 2 and "video.mp4: video not found" in r.stderr
    assert (tmp_path / "run" / "notes.txt").read_text() == "mine"


def test_the_shared_layout_and_what_ingest_writes_pass_the_meta_check(clip_arrays, tmp_path, shared_data):
    for meta_file in sorted((shared_data / "faces").glob("*/meta.json")):
        check_ingest_meta(json.loads(meta_file.read_text()), meta_file)
    d = _folder(tmp_path, *clip_arrays)
    assert len(load_sequence(d)) == 24


@pytest.mark.parametrize("field, value", [("video", []), ("video.width", 0), ("video.fps", True),
                                          ("video.fps", float("inf")), ("landmarks.shape", [3, 68]),
                                          ("landmarks.max_frames", 0), ("name", 3)])
def test_meta_fields_each_name_what_they_expect(field, value):
    meta = {"video": {"fps": 25.0}, "landmarks": {"shape": [3, 68, 2]}}
    parent, _, key = field.rpartition(".")
    (meta[parent] if parent else meta)[key] = value
    with pytest.raises(FacesynthError, match=rf"^m\.json: {field} must be .*, got "):
        check_ingest_meta(meta, "m.json")
