"""The talking-head surfaces as a careless user meets them (issue 43, the command-line side):
``facesynth export RUN --talking-head`` (outputs that are the run's own files, a device, a
name ending in '/', a broken ``config.yaml``, Ctrl-C, no empty folders left), what a
talking-head file is (``runtime.talking_head.check_talking_head_file``: a corrupt file, a
format string only, a face collapsed to a point) and ``facesynth app`` with one (a full disk,
landmarks that disagree with their ``meta.json``, a truncated video, complex landmarks, the
wrong point count). Each case: the exit code, one line naming the file or field, no
traceback, and what is on disk afterwards."""

from __future__ import annotations

import json
import os
import shutil
import stat
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _disk import full_tmpfs
from _errors import one_error_line
from _onnx_models import synthetic_talking_head

from facesynth.cli import main
from facesynth.contract import TALKING_HEAD_FORMAT
from facesynth.errors import FacesynthError

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def _listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def _hidden_temps(d: Path) -> list[str]:
    return [p.name for p in d.iterdir() if ".facesynth-tmp-" in p.name]


@pytest.fixture(scope="module")
def head(tmp_path_factory) -> Path:
    """A good talking-head file of the built-in synthetic subject (tests/_onnx_models.py)."""
    return synthetic_talking_head(tmp_path_factory.mktemp("head"))


@pytest.fixture(scope="module")
def driver(tmp_path_factory) -> Path:
    """(40, 68, 2) landmarks of the synthetic subject with another seed: a driver in the head's frame."""
    from facesynth.data.synthetic import make_synthetic_sequence

    path = tmp_path_factory.mktemp("driver") / "lm.npy"
    np.save(path, make_synthetic_sequence(n_frames=40, size=128, seed=5).landmarks)
    return path


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A small ``facesynth train`` run of the synthetic subject (linear, 8 components, 40 frames)."""
    run = tmp_path_factory.mktemp("train") / "run"
    train = [sys.executable, "-m", "facesynth", "train", "regressor=linear", "eval.frame_level=false",
             "eval.train_level=false", "eval.common_region=false", "eval.noise=[0]", "model.n_appearance=8",
             "data.n_frames=40", "data.size=128", f"hydra.run.dir={run}", "quiet=true"]
    subprocess.run(train, check=True, capture_output=True, timeout=600, env=ENV, cwd=ROOT)
    return run


def _copy_run(run_dir: Path, where: Path) -> Path:
    run = where / "run"
    shutil.copytree(run_dir, run)
    return run


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _video_run(run_dir: Path, tmp_path: Path) -> tuple[Path, Path]:
    """A copy of ``run_dir`` whose config.yaml names an ingest folder of its 40 landmarks (no video)."""
    from facesynth.data.synthetic import make_synthetic_sequence

    run = _copy_run(run_dir, tmp_path)
    data = tmp_path / "ingested"
    data.mkdir()
    lm = make_synthetic_sequence(n_frames=40, size=128, seed=0).landmarks
    np.save(data / "landmarks.npy", lm)
    (data / "meta.json").write_text(json.dumps({"landmarks": {"shape": list(lm.shape)}}))
    cfg = (run / "config.yaml").read_text().replace("kind: synthetic", "kind: video").replace(
        "path: null", f"path: {data}")
    (run / "config.yaml").write_text(cfg)
    return run, data


# ------------------------------------------------------------------ export --talking-head
@pytest.mark.parametrize("talking_head", [True, False])
def test_export_refuses_to_overwrite_the_runs_own_files(run_dir, tmp_path, capsys, talking_head):
    """``--out`` on the run's face model or on its training landmarks.npy: exit 2, one line
    naming it, every file of the run and of its data byte-identical (the run still loads)."""
    from facesynth.sadm.fit import load_sadm

    run, data = _video_run(run_dir, tmp_path)
    before, data_before = _snapshot(run), _snapshot(data)
    flag = ["--talking-head"] if talking_head else []
    for out in (run / "face_model" / "face_model.safetensors", data / "landmarks.npy", run / "config.yaml"):
        assert main(["export", str(run), "--out", str(out), *flag, "--quiet"]) == 2
        one_error_line(capsys.readouterr().err, str(out), "the output is the input")
    assert _snapshot(run) == before and _snapshot(data) == data_before
    load_sadm(run)


def test_export_never_replaces_a_device_or_a_pipe(run_dir, tmp_path, capsys):
    """An existing character device (a copy of /dev/null, root only) or FIFO as ``--out``:
    exit 2, one line, the node still what it was (was: replaced by a 10 MB regular file)."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    nodes = [fifo]
    if os.geteuid() == 0:
        null = tmp_path / "null"
        os.mknod(null, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        nodes.append(null)
    for node in nodes:
        kind = stat.S_IFMT(node.lstat().st_mode)
        assert main(["export", str(run_dir), "--talking-head", "--out", str(node), "--quiet"]) == 2
        one_error_line(capsys.readouterr().err, str(node), "not a regular file")
        assert stat.S_IFMT(node.lstat().st_mode) == kind
    assert sorted(_listing(tmp_path)) == sorted(n.name for n in nodes)


def test_export_out_ending_in_a_slash_is_a_folder_name(run_dir, tmp_path, capsys):
    """``--out DIR/newdir/``: exit 2 naming it, and no file (or folder) named newdir."""
    out = f"{tmp_path}/newdir/"
    assert main(["export", str(run_dir), "--talking-head", "--out", out, "--quiet"]) == 2
    one_error_line(capsys.readouterr().err, out, "ends with '/'")
    assert _listing(tmp_path) == []


@pytest.mark.parametrize("config", ["malformed", "without_data", "a_list", "without_a_data_field"])
def test_export_with_a_broken_config_is_one_line(run_dir, tmp_path, capsys, config):
    """RUN/config.yaml not YAML, without ``data``, a YAML list, or missing a ``data`` field:
    ``export --talking-head``, and a plain export that compresses (it reads the training
    landmarks the config names), exit 2 with one line naming the file (was a ParserError or
    ConfigAttributeError traceback, exit 1): no output, no folder."""
    run = _copy_run(run_dir, tmp_path)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text({
        "malformed": "data: [\n",
        "without_data": "".join(line + "\n" for line in text.splitlines()
                                if not line.startswith("data:") and not line.startswith("  ")),
        "a_list": "- data\n- seed\n",
        "without_a_data_field": text.replace("  train_fraction: 0.75\n", ""),
    }[config])
    out = tmp_path / "new" / "head.onnx"
    for flags in (["--talking-head"], ["--components", "4"]):
        assert main(["export", str(run), *flags, "--out", str(out), "--quiet"]) == 2
        err = one_error_line(capsys.readouterr().err, str(run / "config.yaml"))
        if config == "without_a_data_field":
            assert "data.train_fraction" in err
        assert not (tmp_path / "new").exists()


def test_a_refused_export_leaves_no_folders(run_dir, tmp_path, capsys):
    """A talking-head export refused once its output file was opened (the run's data has no
    video, so no avatar frame): exit 2 naming the run, and the missing folders of ``--out``
    it had made are removed again (docs/reliability.md: a refused run leaves none)."""
    run, _ = _video_run(run_dir, tmp_path)
    out = tmp_path / "a" / "b" / "head.onnx"
    assert main(["export", str(run), "--talking-head", "--out", str(out), "--quiet"]) == 2
    one_error_line(capsys.readouterr().err, str(run), "no avatar neutral and frame")
    assert not (tmp_path / "a").exists()


CTRL_C = """
import atexit, logging, sys
from facesynth import cli
import facesynth.onnx.cli as export_cli  # the command's run: patched to be interrupted

def interrupted(args):  # a library that logs at exit, as torch's FakeTensor cache statistics do
    atexit.register(lambda: logging.getLogger("torch._subclasses.fake_tensor").info("FakeTensor cache stats:"))
    raise KeyboardInterrupt

export_cli.run = interrupted
sys.exit(cli.main(sys.argv[1:]))
"""


def test_ctrl_c_is_the_last_line(run_dir, tmp_path):
    """Ctrl-C during ``export``: ``interrupted`` is the last line, exit 130; an INFO line that a
    library logs at exit (torch's cache statistics did) does not follow it."""
    p = subprocess.run([sys.executable, "-c", CTRL_C, "export", str(run_dir), "--talking-head", "--out",
                        str(tmp_path / "h.onnx")], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=300)
    assert p.returncode == 130 and p.stderr.splitlines()[-1] == "interrupted", p.stderr
    assert "INFO" not in p.stderr


# ------------------------------------------------------------------ what a talking-head file is
def _overwrite_weights(src: Path, dst: Path, name: str, n: int = 65536) -> Path:
    """``src`` with ``n`` random bytes written into the middle of initializer ``name``'s data:
    the metadata intact, the file still parses."""
    import onnx

    data = src.read_bytes()
    t = next(t for t in onnx.load(str(src)).graph.initializer if t.name == name)
    at = data.find(t.raw_data)
    assert at > 0 and len(t.raw_data) >= n
    at += (len(t.raw_data) - n) // 2
    dst.write_bytes(data[:at] + np.random.default_rng(0).integers(0, 256, n, np.uint8).tobytes() + data[at + n:])
    return dst


def _format_only(path: Path) -> Path:
    """A one-node graph carrying only the talking-head format string."""
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])
    helper.set_model_props(m, {"format": TALKING_HEAD_FORMAT})
    onnx.save(m, str(path))
    return path


@pytest.fixture(scope="module")
def bad_heads(head, tmp_path_factory) -> dict:
    """Files that are no working talking head: 64 KiB of the weights overwritten where the
    graph then renders garbage (the appearance mean) and where it cannot run (the frame
    warp's index table), and a format string on a one-node graph."""
    d = tmp_path_factory.mktemp("bad")
    return {"garbage_weights": _overwrite_weights(head, d / "garbage.onnx", "synthesis.app_mean"),
            "broken_indices": _overwrite_weights(head, d / "indices.onnx", "frame_warp.ev_index"),
            "format_only": _format_only(d / "format_only.onnx")}


def test_the_check_accepts_a_good_file_and_returns_its_metadata(head):
    from facesynth.runtime.talking_head import check_talking_head_file

    meta = check_talking_head_file(head)
    assert meta["format"] == TALKING_HEAD_FORMAT and meta["n_landmarks"] == 68


@pytest.mark.parametrize("case, needle", [("garbage_weights", "corrupt weights"),
                                          ("broken_indices", "fails on the avatar's own neutral"),
                                          ("format_only", "without the metadata")])
def test_the_check_refuses_what_cannot_run(bad_heads, case, needle):
    from facesynth.runtime.talking_head import check_talking_head_file

    path = bad_heads[case]
    with pytest.raises(FacesynthError, match=needle) as exc:
        check_talking_head_file(path)
    assert str(exc.value).startswith(str(path)) and "\n" not in str(exc.value)


def test_the_check_holds_the_graph_to_the_contract(head, tmp_path):
    """A talking head whose output is renamed, or whose frame output is float: refused, naming
    the file and the output (the contract: facesynth/contract.py TALKING_HEAD_SIGNATURE)."""
    import onnx
    from onnx import TensorProto, helper

    from facesynth.runtime.talking_head import check_talking_head_file

    m = onnx.load(str(head))
    renamed = onnx.ModelProto()
    renamed.CopyFrom(m)
    for node in renamed.graph.node:
        node.output[:] = ["picture" if o == "frame" else o for o in node.output]
    renamed.graph.output[0].name = "picture"
    onnx.save(renamed, str(tmp_path / "renamed.onnx"))
    with pytest.raises(FacesynthError, match=r"graph outputs \['picture', 'avatar_landmarks'\]"):
        check_talking_head_file(tmp_path / "renamed.onnx")
    m.graph.node.append(helper.make_node("Cast", ["frame"], ["frame_f"], to=TensorProto.FLOAT))
    m.graph.output[0].CopyFrom(helper.make_tensor_value_info("frame_f", TensorProto.FLOAT, ["B", "H", "W", 3]))
    m.graph.output[0].name = "frame_f"
    for node in m.graph.node[:-1]:
        node.output[:] = ["frame_u8" if o == "frame" else o for o in node.output]
    m.graph.node[-1].input[:] = ["frame_u8"]
    m.graph.node[-1].output[:] = ["frame"]
    m.graph.output[0].name = "frame"
    onnx.save(m, str(tmp_path / "float.onnx"))
    with pytest.raises(FacesynthError, match="graph output 'frame' is float32 of rank 4, a talking head's is uint8"):
        check_talking_head_file(tmp_path / "float.onnx")


@pytest.mark.parametrize("case", ["garbage_weights", "broken_indices", "format_only"])
def test_app_refuses_a_file_that_is_no_talking_head(bad_heads, driver, tmp_path, capsys, case):
    """``app --model`` on each: exit 2, one line naming the model (was a GatherElements
    traceback, ``KeyError: 'feather'``, or a garbage video with exit 0), no output."""
    out = tmp_path / "o" / "v.mp4"
    assert main(["app", "--model", str(bad_heads[case]), "--landmarks", str(driver), "--out", str(out),
                 "--no-progress"]) == 2
    one_error_line(capsys.readouterr().err, str(bad_heads[case]))
    assert not out.parent.exists()


def test_app_refuses_a_face_collapsed_to_a_point(head, driver, tmp_path, capsys):
    """Every point of every frame on one pixel: one line naming the landmarks file (was a
    traceback from ONNX Runtime's Range node); the runtime refuses it too."""
    from facesynth.runtime.talking_head import TalkingHead

    lm = np.load(driver)
    np.save(tmp_path / "dot.npy", np.full_like(lm, 64.0))
    assert main(["app", "--model", str(head), "--landmarks", str(tmp_path / "dot.npy"), "--out",
                 str(tmp_path / "o.mp4"), "--no-progress"]) == 2
    one_error_line(capsys.readouterr().err, str(tmp_path / "dot.npy"), "degenerate faces")
    th = TalkingHead(head, driver_neutral=lm[0])
    with pytest.raises(FacesynthError, match="driver landmarks: degenerate faces"):
        th.step(np.full(lm.shape[1:], 64.0, np.float32))
    with pytest.raises(FacesynthError, match="driver_neutral: degenerate faces"):
        th.use_neutral(np.full(lm.shape[1:], 64.0, np.float32))
    assert _listing(tmp_path) == ["dot.npy"]


# ------------------------------------------------------------------ app: the driver
def test_app_refuses_complex_landmarks(head, driver, tmp_path, capsys):
    np.save(tmp_path / "c.npy", np.load(driver).astype(np.complex64))
    assert main(["app", "--model", str(head), "--landmarks", str(tmp_path / "c.npy"), "--out",
                 str(tmp_path / "o.mp4"), "--no-progress"]) == 2
    one_error_line(capsys.readouterr().err, str(tmp_path / "c.npy"), "real numbers", "complex64")
    assert _listing(tmp_path) == ["c.npy"]


def test_app_refuses_an_ingest_folder_whose_landmarks_disagree_with_meta_json(head, driver, tmp_path, capsys):
    """landmarks.npy with 10 rows, meta.json saying 40: refused as training's loader refuses
    it (one line naming landmarks.npy and both shapes); was rendered anyway."""
    from facesynth.data import load_sequence

    folder = tmp_path / "ingested"
    folder.mkdir()
    np.save(folder / "landmarks.npy", np.load(driver)[:10])
    (folder / "meta.json").write_text(json.dumps({"landmarks": {"shape": [40, 68, 2]}, "video": {"fps": 25}}))
    assert main(["app", "--model", str(head), "--landmarks", str(folder), "--out", str(tmp_path / "o.mp4"),
                 "--no-progress"]) == 2
    err = one_error_line(capsys.readouterr().err, str(folder / "landmarks.npy"), "[10, 68, 2]", "[40, 68, 2]")
    with pytest.raises(FacesynthError) as exc:  # training's loader: the same message
        load_sequence(folder)
    assert str(exc.value) == err[len("error: "):].strip()
    assert _listing(tmp_path) == ["ingested"]


def test_68_points_for_a_478_point_model_names_the_file(driver, tmp_path):
    """What ``app --landmarks FOLDER`` reads for a 478-point model (``load_landmarks(...,
    scheme='mediapipe478')``): the error names the folder's landmarks.npy, not the folder."""
    from facesynth.data import load_landmarks

    folder = tmp_path / "clip"
    folder.mkdir()
    np.save(folder / "landmarks.npy", np.load(driver))
    (folder / "meta.json").write_text(json.dumps({"landmarks": {"shape": [40, 68, 2]}}))
    for given, named in ((folder, folder / "landmarks.npy"), (driver, driver)):
        with pytest.raises(FacesynthError) as exc:
            load_landmarks(given, scheme="mediapipe478")
        assert str(exc.value).startswith(f"{named}: ibug68 landmarks cannot be mapped to mediapipe478"), exc.value


def _faststart(src: Path, dst: Path) -> Path:
    """``src`` (an mp4 whose index, the moov box, follows its frames) with the index moved to the
    front, as a "faststart" file: every chunk offset (stco / co64) moved by the index's size."""
    data = src.read_bytes()
    boxes, i = [], 0
    while i < len(data):
        size, kind = struct.unpack(">I4s", data[i:i + 8])
        size = struct.unpack(">Q", data[i + 8:i + 16])[0] if size == 1 else size or len(data) - i
        boxes.append((kind, data[i:i + size]))
        i += size
    moov = bytearray(next(b for k, b in boxes if k == b"moov"))

    def patch(start: int, end: int) -> None:
        j = start
        while j < end:
            size, kind = struct.unpack(">I4s", moov[j:j + 8])
            if kind in (b"trak", b"mdia", b"minf", b"stbl"):
                patch(j + 8, j + size)
            elif kind in (b"stco", b"co64"):
                fmt, width = (">I", 4) if kind == b"stco" else (">Q", 8)
                for k in range(struct.unpack(">I", moov[j + 12:j + 16])[0]):
                    at = j + 16 + width * k
                    struct.pack_into(fmt, moov, at, struct.unpack(fmt, moov[at:at + width])[0] + len(moov))
            j += size

    patch(8, len(moov))
    kinds = [k for k, _ in boxes]
    assert kinds.index(b"mdat") < kinds.index(b"moov")
    head = [b for k, b in boxes[:kinds.index(b"mdat")]]
    tail = [b for k, b in boxes[kinds.index(b"mdat"):] if k != b"moov"]
    dst.write_bytes(b"".join([*head, bytes(moov), *tail]))
    return dst


def test_a_truncated_video_is_said_to_be(head, driver, tmp_path, caplog, monkeypatch):
    """A faststart mp4 cut in half (60 frames declared, fewer decode) as ``app --video``: a
    warning naming the file and both counts, and the frames that decode rendered (the output
    reopens whole with that many frames); was 0 words. A warning, not an error: what decodes
    is good, the output holds exactly it, and a recording cut short is still worth driving."""
    import facesynth.data.detect as detect

    lm = np.load(driver)
    frames = [np.full((128, 128, 3), 40 + 3 * i, np.uint8) for i in range(60)]
    whole = tmp_path / "whole.mp4"
    w = cv2.VideoWriter(str(whole), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (128, 128))
    for f in frames:
        w.write(f)
    w.release()
    fast = _faststart(whole, tmp_path / "fast.mp4")
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(fast.read_bytes()[: fast.stat().st_size * 2 // 3])
    cap = cv2.VideoCapture(str(cut))
    declared, decoded = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0
    while cap.read()[0]:
        decoded += 1
    cap.release()
    assert declared == 60 and 10 < decoded < 60

    def fake_detect(frames, detector=None, on_frame=None):  # dlib (an extra) replaced: the driver's rows in turn
        n = len(list(frames))
        return detect.Detections(lm[np.arange(n) % len(lm)], np.zeros((n, 4), np.float32), ["hog_up0"] * n,
                                 np.ones(n, int))

    monkeypatch.setattr(detect, "check_extra", lambda: None)
    monkeypatch.setattr(detect, "detect_landmarks", fake_detect)
    out = tmp_path / "o.mp4"
    assert main(["app", "--model", str(head), "--video", str(cut), "--out", str(out), "--no-progress"]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and str(cut) in warned[0] and f"only {decoded} of the 60 frames" in warned[0], warned
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == decoded
    cap.release()


# ------------------------------------------------------------------ app: a full disk
def test_a_full_disk_at_the_writers_opening_is_said_so(head, driver, tmp_path, capsys, monkeypatch):
    """Faked, for any user: the mp4v writer does not open and the file system is full: "no space
    left on device" naming the file, not the codec message."""
    import facesynth.videofile as videofile

    class Closed:
        def __init__(self, *a):
            pass

        def isOpened(self):
            return False

        def release(self):
            pass

    monkeypatch.setattr(cv2, "VideoWriter", Closed)
    monkeypatch.setattr(videofile, "free_bytes", lambda path: 0)
    out = tmp_path / "o.mp4"
    assert main(["app", "--model", str(head), "--landmarks", str(driver), "--out", str(out), "--no-progress"]) == 2
    one_error_line(capsys.readouterr().err, f"no space left on device writing {out}")
    assert _listing(tmp_path) == []
    monkeypatch.setattr(videofile, "free_bytes", lambda path: 1 << 30)  # room: then it is the name's fault
    assert main(["app", "--model", str(head), "--landmarks", str(driver), "--out", str(out), "--no-progress"]) == 2
    one_error_line(capsys.readouterr().err, "OpenCV cannot write an mp4v video here")


@pytest.mark.parametrize("room", ["none", "a_third"])
def test_a_full_tmpfs_is_one_line(head, driver, tmp_path, room):
    """A real 3 MB tmpfs, filled with dd to leave no room, or a third of the video's size:
    exit 2, the one line "no space left on device writing PATH" (was the mp4v codec message,
    or OpenCV's "Failed to write frame" warnings before the right line), nothing left."""
    lm = np.concatenate([np.load(driver)] * 10)  # 400 frames
    np.save(tmp_path / "lm.npy", lm)
    app = [sys.executable, "-m", "facesynth", "app", "--model", str(head), "--landmarks", str(tmp_path / "lm.npy"),
           "--quiet"]
    ok = subprocess.run([*app, "--out", str(tmp_path / "whole.mp4")], capture_output=True, text=True, env=ENV)
    assert ok.returncode == 0, ok.stderr
    need = (tmp_path / "whole.mp4").stat().st_size
    with full_tmpfs(tmp_path / "M", size="3M", leave_kb=0 if room == "none" else max(4, need // 3 // 1024)) as mnt:
        p = subprocess.run([*app, "--out", str(mnt / "o.mp4")], capture_output=True, text=True, env=ENV)
        assert p.returncode == 2, (p.stdout, p.stderr)
        assert p.stderr == f"error: no space left on device writing {mnt / 'o.mp4'}\n", p.stderr
        assert _listing(mnt) == ["filler"]
