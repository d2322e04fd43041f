"""The talking head in one ONNX graph (facesynth.onnx.talking_head) against the numpy
reference pipeline (Reenactor with the full-frame warp, relative motion, the graph's
feather), on a shared clip, for a 68-point and a 478-point avatar: the retargeted
landmarks, every pixel of the composited frames, the runtime."""

from __future__ import annotations

import numpy as np
import pytest

from facesynth.errors import FacesynthError

FRAMES = 12


def _driver(scheme: str, shared_clip_dir, shared_mesh_npz) -> tuple[np.ndarray, np.ndarray]:
    """lp_d13's neutral (P, 2) and FRAMES of its frames (FRAMES, P, 2) in ``scheme``."""
    from facesynth.runtime.reenact import driver_neutral_of

    lm = np.load(shared_clip_dir("lp_d13") / "landmarks.npy").astype(np.float32)
    _, row = driver_neutral_of(lm)
    rows = [row, *np.linspace(0, len(lm) - 1, FRAMES).astype(int)]
    if scheme == "mediapipe478":
        from _dense import template478, to478

        dense = to478(lm[rows], template478(shared_mesh_npz()))
        return dense[0], dense[1:]
    return lm[row], lm[rows[1:]]


@pytest.fixture(scope="module", params=["ibug68", "mediapipe478"])
def head(request, shared_clip_dir, tmp_path_factory):
    """A small linear model of lp_d10 (every 3rd training frame; its 478 points: MediaPipe's
    canonical mesh bent onto its 68, tests/_dense.py), its synthesis file with the avatar
    metadata and its talking-head file."""
    from _onnx_models import linear_avatar

    from facesynth.data import load_sequence, temporal_split
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.onnx.talking_head import export_talking_head

    seq = load_sequence(shared_clip_dir("lp_d10"))
    if request.param == "mediapipe478":
        from _dense import dense_sequence

        seq = dense_sequence(seq, _mesh_npz())
    train, _ = temporal_split(len(seq))
    syn, meta = linear_avatar(seq, train)
    out = tmp_path_factory.mktemp("talking_head")
    export_synthesizer(syn, out / "face.onnx", meta)
    export_talking_head(syn, meta, out / "head.onnx")
    return request.param, out / "face.onnx", out / "head.onnx"


def _mesh_npz():
    from facesynth.data.shared import shared_mesh_dir

    d = shared_mesh_dir()
    if d is None:
        pytest.skip("../shared/data/mesh is absent")
    return d / "mediapipe_canonical_468_arrays.npz"


def test_graph_matches_the_numpy_pipeline(head, shared_clip_dir):
    from facesynth.runtime import Reenactor
    from facesynth.runtime.talking_head import TalkingHead

    scheme, face, path = head
    neutral, frames = _driver(scheme, shared_clip_dir, _mesh_npz)
    th = TalkingHead(path, driver_neutral=neutral)
    assert th.n_points == neutral.shape[0]
    ref = Reenactor(face, driver_neutral=neutral, feather=th.feather, full_frame=True)
    worst_lm, worst = 0.0, 0
    for lm in frames:
        want, want_lm = ref.step(lm)
        got, got_lm = th.step(lm)
        assert got.dtype == np.uint8 and got.shape == want.shape
        worst_lm = max(worst_lm, float(np.abs(got_lm - want_lm).max()))
        worst = max(worst, int(np.abs(got.astype(int) - want).max()))
    assert worst_lm <= 0.05
    assert worst <= 2  # every pixel of every frame


def test_runtime_chooses_the_drivers_neutral_and_checks_its_input(head, shared_clip_dir):
    from facesynth.runtime.talking_head import TalkingHead

    scheme, face, path = head
    _, lm = _driver(scheme, shared_clip_dir, _mesh_npz)
    lm = lm[:3]
    th = TalkingHead(path, neutral_frames=2)
    for row in lm:
        frame, avatar = th.step(row)
    assert frame.shape == (*th.frame_size[::-1], 3) and avatar.shape == lm.shape[1:]
    assert th.driver_neutral is not None and not th._online.choosing
    frames, avatars = th.run(lm)  # a batch renders as its frames one at a time
    one, _ = th.run(lm[1:2])
    assert frames.shape[0] == 3 and np.abs(frames[1].astype(int) - one[0]).max() <= 2
    with pytest.raises(FacesynthError, match="driver landmarks"):
        th.step(np.full(lm.shape[1:], np.nan, np.float32))
    with pytest.raises(FacesynthError, match="not a talking-head graph"):
        TalkingHead(face)


def test_export_and_app_run_a_talking_head_file(tmp_path, capsys):
    """``facesynth export RUN --talking-head`` writes a checked talking-head file; ``facesynth
    app`` renders every driver frame with it (the avatar landmarks it saves are the graph's
    own), and refuses, with exit 2 and no output, the options the file fixes at export."""
    import json
    import subprocess
    import sys

    import cv2

    from facesynth.cli import main
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.runtime.talking_head import TalkingHead

    run = tmp_path / "run"
    train = [sys.executable, "-m", "facesynth", "train", "regressor=linear", "eval.frame_level=false",
             "eval.train_level=false", "eval.common_region=false", "eval.noise=[0]", "model.n_appearance=8",
             "data.n_frames=40", "data.size=128", f"hydra.run.dir={run}", "quiet=true"]
    subprocess.run(train, check=True, capture_output=True, timeout=300)
    head = tmp_path / "head.onnx"
    assert main(["export", str(run), "--out", str(head), "--talking-head", "--quiet", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["talking_head"] and summary["max_abs_diff_vs_torch"] <= 2
    # without --json a person reads one short line: what was written, its size, its check
    from facesynth.onnx.export import summary_line

    line = summary_line(summary)
    assert len(json.dumps(summary)) > 1000 and len(line) - len(str(head)) < 100 and "\n" not in line, line
    assert line.startswith(f"wrote {head} (talking head, ") and "ONNX Runtime vs torch" in line
    lm = make_synthetic_sequence(n_frames=12, size=128, seed=5).landmarks
    np.save(tmp_path / "lm.npy", lm)
    out, saved = tmp_path / "o.mp4", tmp_path / "avatar.npy"
    assert main(["app", "--model", str(head), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(out),
                 "--save-landmarks", str(saved), "--driver-neutral", "0", "--no-progress", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["talking_head_graph"] is True
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == len(lm) and cap.read()[0]
    cap.release()
    _, want = TalkingHead(head, driver_neutral=lm[0]).run(lm)
    np.testing.assert_allclose(np.load(saved), want, atol=1e-4)
    bad = tmp_path / "bad.mp4"
    assert main(["app", "--model", str(head), "--landmarks", str(tmp_path / "lm.npy"), "--out", str(bad),
                 "--feather", "3", "--no-progress"]) == 2
    assert "--feather cannot apply" in capsys.readouterr().err and not bad.exists()


def test_the_reports_talking_head_figures():
    """eval.talking_head: the synthetic avatar driving itself on held-out frames; the static
    renderer's figures recomputed here from the avatar's neutral frame (as exported: JPEG) and
    the real frames; every figure a PSNR / SSIM; the strip's tiles."""
    from _faces import face_sequence_arrays
    from _onnx_models import synthetic_synthesizer

    from facesynth.data import FaceSequence, temporal_split
    from facesynth.data.frames import ArrayFrames
    from facesynth.eval.talking_head import talking_head_figures
    from facesynth.landmarks import ibug68_view
    from facesynth.metrics import psnr
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.runtime.fullframe import head_region
    from facesynth.runtime.reenact import Avatar

    frames, lm = face_sequence_arrays(n=24, seed=1)  # the frames synthetic_model() was fitted on
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    syn = synthetic_synthesizer("linear")
    train, test = temporal_split(len(seq))
    figures, tiles = talking_head_figures(syn, seq, train, test, frames=4, strip=3)
    assert figures["frames"] == 4 and figures["neutral_row"] in train
    avatar = Avatar(avatar_metadata(syn, lm[train], train, seq))
    background = avatar.background
    assert figures["ring_scale"] == avatar.ring_scale  # the warp the export carries
    rows = test[np.unique(np.linspace(0, len(test) - 1, 4).round().astype(int))]
    want = np.mean([psnr(background, frames[r], head_region(ibug68_view(lm[r]), frames[r].shape[1::-1])) for r in rows])
    assert figures["static"]["psnr_head_db"] == pytest.approx(want, abs=0.01)
    for r in ("static", "warp", "full"):
        assert 0 < figures[r]["ssim_head"] <= 1 and 0 < figures[r]["ssim_frame"] <= 1 and figures[r]["psnr_frame_db"] > 5
    assert figures["full"] != figures["warp"]  # the synthesised face is in it
    outline = figures["outline"]  # the warp's grid against its exact map (tests/test_jaggedness.py)
    assert set(outline) == {"map_px_p99", "map_px_max", "staircase"}
    assert 0 <= outline["map_px_p99"] <= outline["map_px_max"] and outline["staircase"] >= 0
    assert len(tiles) == 3 and tiles[0]["real"].shape == tiles[0]["synth"].shape
