"""The talking head in one ONNX graph (facesynth.onnx.talking_head) against the numpy
reference pipeline (Reenactor with the full-frame warp, relative motion, the graph's
feather), on a shared clip: the retargeted landmarks, the composited frames, the runtime."""

from __future__ import annotations

import numpy as np
import pytest

from facesynth.errors import FacesynthError

FRAMES = 12


@pytest.fixture(scope="module")
def head(shared_clip_dir, tmp_path_factory):
    """A small linear model of lp_d10 (every 3rd training frame), its synthesis file with the
    avatar metadata and its talking-head file."""
    from _onnx_models import linear_avatar

    from facesynth.data import load_sequence, temporal_split
    from facesynth.onnx.synthesis import export_synthesizer
    from facesynth.onnx.talking_head import export_talking_head

    seq = load_sequence(shared_clip_dir("lp_d10"))
    train, _ = temporal_split(len(seq))
    syn, meta = linear_avatar(seq, train)
    out = tmp_path_factory.mktemp("talking_head")
    export_synthesizer(syn, out / "face.onnx", meta)
    export_talking_head(syn, meta, out / "head.onnx")
    return out / "face.onnx", out / "head.onnx"


def test_graph_matches_the_numpy_pipeline(head, shared_clip_dir):
    from facesynth.runtime import Reenactor
    from facesynth.runtime.reenact import driver_neutral_of
    from facesynth.runtime.talking_head import TalkingHead

    face, path = head
    lm = np.load(shared_clip_dir("lp_d13") / "landmarks.npy").astype(np.float32)
    neutral, _ = driver_neutral_of(lm)
    th = TalkingHead(path, driver_neutral=neutral)
    ref = Reenactor(face, driver_neutral=neutral, feather=th.feather, full_frame=True)
    worst_lm, worst = 0.0, 0
    for i in np.linspace(0, len(lm) - 1, FRAMES).astype(int):
        want, want_lm = ref.step(lm[i])
        got, got_lm = th.step(lm[i])
        assert got.dtype == np.uint8 and got.shape == want.shape
        worst_lm = max(worst_lm, float(np.abs(got_lm - want_lm).max()))
        worst = max(worst, int(np.abs(got.astype(int) - want).max()))
    assert worst_lm <= 0.05
    assert worst <= 2  # every pixel of every frame


def test_runtime_chooses_the_drivers_neutral_and_checks_its_input(head, shared_clip_dir):
    from facesynth.runtime.talking_head import TalkingHead

    face, path = head
    lm = np.load(shared_clip_dir("lp_d13") / "landmarks.npy")[:3].astype(np.float32)
    th = TalkingHead(path, neutral_frames=2)
    for row in lm:
        frame, avatar = th.step(row)
    assert frame.shape == (*th.frame_size[::-1], 3) and avatar.shape == (68, 2)
    assert th.driver_neutral is not None and not th._collecting
    frames, avatars = th.run(lm)  # a batch renders as its frames one at a time
    one, _ = th.run(lm[1:2])
    assert frames.shape[0] == 3 and np.abs(frames[1].astype(int) - one[0]).max() <= 2
    with pytest.raises(FacesynthError, match="driver landmarks"):
        th.step(np.full((68, 2), np.nan, np.float32))
    with pytest.raises(FacesynthError, match="not a talking-head graph"):
        TalkingHead(face)
