"""Each exported file kind read against facesynth/contract.py: every metadata field a file
carries is declared in ``METADATA_FIELDS`` (its order and unit written once), and the sizes
hold the declared order, checked against the arrays they describe: ``frame_size`` [W, H]
against the frame the file places its output in (the avatar's neutral frame, the ERI target's
image, the talking head's output), ``canvas_size`` [H, W] against the rendered crop's shape.
An ERI file of the first format (frame_size (H, W)) is still read in its own order."""

from __future__ import annotations

import base64

import cv2
import numpy as np
import onnx
import pytest
from _onnx_models import synthetic_talking_head

from facesynth.contract import ERI_FORMAT_V1, METADATA_FIELDS
from facesynth.runtime import EriRenderer, Renderer, TalkingHead, read_metadata


@pytest.fixture(scope="module")
def files(tmp_path_factory, model, seq):
    """The three kinds: a synthesis file with the avatar's metadata, its talking head, an ERI file."""
    from facesynth.data import temporal_split
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.eri.synthesis import EriSynthesizer
    from facesynth.onnx.eri import export_eri
    from facesynth.onnx.synthesis import export_synthesizer

    out = tmp_path_factory.mktemp("contract")
    head = synthetic_talking_head(out)
    meta = read_metadata(head)
    # the synthesis file of the same subject, with the avatar metadata the talking head carries
    from _onnx_models import fit_synthesizer

    from facesynth.model import FaceModel, FaceModelConfig

    subject = make_synthetic_sequence(n_frames=40, size=128, seed=0)
    train, _ = temporal_split(len(subject))
    fm = FaceModel.fit(subject, FaceModelConfig(n_appearance=8), rows=train, progress=False)
    syn = fit_synthesizer("linear", fm, fm.shape_params(subject.landmarks[train], clamp=True),
                          fm.appearance_params(fm.sample_textures(subject, train), clamp=True))
    avatar = {k: meta[k] for k in ("avatar_neutral", "avatar_neutral_row", "avatar_neutral_rule", "shape_pca",
                                   "background_jpeg", "frame_size", "frame_motion") if k in meta}
    face = export_synthesizer(syn, out / "face.onnx", avatar)
    target = seq.frame(0)[:, :-7], seq.landmarks[0]  # a target image that is not square
    eri = export_eri(EriSynthesizer(model, *target), out / "eri.onnx")
    return {"face": face, "head": head, "eri": eri, "target": target[0]}


def _jpeg_size(meta: dict) -> list[int]:
    img = cv2.imdecode(np.frombuffer(base64.b64decode(meta["background_jpeg"]), np.uint8), cv2.IMREAD_COLOR)
    return [img.shape[1], img.shape[0]]


@pytest.mark.parametrize("kind", ["face", "head", "eri"])
def test_every_metadata_field_is_declared(files, kind):
    undeclared = set(read_metadata(files[kind])) - set(METADATA_FIELDS)
    assert undeclared == set()


def test_an_ibug68_avatar_carries_no_coverage_recording(files):
    """The live reach readout needs the irises: 68-point avatars have no coverage_recording (the page
    hides the readout; tests/test_web_page.py)."""
    head = read_metadata(files["head"])
    assert head["landmark_scheme"] == "ibug68" and "coverage_recording" not in head


def test_frame_size_is_width_then_height_in_every_file(files):
    face, head, eri = (read_metadata(files[k]) for k in ("face", "head", "eri"))
    h, w = files["target"].shape[:2]
    assert w != h and eri["frame_size"] == [w, h]
    assert EriRenderer(files["eri"]).frame_size == (w, h)
    assert face["frame_size"] == _jpeg_size(face) and head["frame_size"] == _jpeg_size(head)
    th = TalkingHead(files["head"], driver_neutral=np.asarray(head["avatar_neutral"], np.float32))
    frame, _ = th.run(np.asarray(head["avatar_neutral"], np.float32)[None])
    assert [frame.shape[2], frame.shape[1]] == head["frame_size"] == list(th.frame_size)


@pytest.mark.parametrize("kind", ["face", "eri"])
def test_canvas_size_is_the_crops_shape(files, kind):
    r = EriRenderer(files[kind]) if kind == "eri" else Renderer(files[kind])
    crops = r.render(np.zeros((1, r.n_faps), np.float32)) if kind == "eri" else \
        r.render(np.asarray(read_metadata(files[kind])["avatar_neutral"], np.float32)[None])
    assert list(crops[0].shape[2:]) == read_metadata(files[kind])["canvas_size"]


def test_a_first_format_eri_file_is_read_in_its_own_order(files, tmp_path):
    """facesynth.eri.onnx/1 wrote frame_size (H, W): the runtime reads those files as they are."""
    m = onnx.load(str(files["eri"]))
    props = {p.key: p for p in m.metadata_props}
    w, h = read_metadata(files["eri"])["frame_size"]
    props["format"].value, props["frame_size"].value = ERI_FORMAT_V1, f"[{h}, {w}]"
    onnx.save(m, str(tmp_path / "v1.onnx"))
    r = EriRenderer(tmp_path / "v1.onnx")
    assert r.frame_size == (w, h)
    assert r.render_frames(np.zeros((1, r.n_faps), np.float32), files["target"]).shape == (1, h, w, 3)
