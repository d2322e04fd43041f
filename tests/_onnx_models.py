"""Small synthesizers (synthetic faces, every registered regressor) and their ONNX exports,
shared by the ONNX/runtime tests. Built once per session; a few seconds in all."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from _faces import face_sequence_arrays

from facesynth.data import FaceSequence
from facesynth.data.frames import ArrayFrames
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.regressors import REGISTRY
from facesynth.sadm.synthesis import GlobalAppearance, Synthesizer


@lru_cache(maxsize=1)
def synthetic_model():
    frames, lm = face_sequence_arrays(n=24, seed=1)
    seq = FaceSequence.from_arrays(lm, ArrayFrames(frames), name="unit")
    model = FaceModel.fit(seq, FaceModelConfig(reference_width=64, appearance_variance=0.95), progress=False)
    x = model.shape_params(lm, clamp=True)
    y = model.appearance_params(model.sample_textures(seq))
    return model, lm, x, y


def fit_synthesizer(name: str, model, x, y) -> Synthesizer:
    torch.manual_seed(0)
    reg = REGISTRY[name].fit(x, y, seed=0)
    syn = Synthesizer(model, GlobalAppearance(model, reg)).eval()
    syn.face_model, syn.regressor_ = model, reg  # kept for save_run_synthesizer in tests
    return syn


@lru_cache(maxsize=None)
def synthetic_synthesizer(name: str = "linear") -> Synthesizer:
    model, _, x, y = synthetic_model()
    return fit_synthesizer(name, model, x, y)


def exported(name: str, directory: Path) -> Path:
    """The ONNX file of :func:`synthetic_synthesizer` (exported once per directory)."""
    from facesynth.onnx.synthesis import export_synthesizer

    path = Path(directory) / f"synthetic_{name}.onnx"
    if not path.is_file():
        model = synthetic_model()[0]
        export_synthesizer(synthetic_synthesizer(name), path, {"data_fingerprint": model.fingerprint})
    return path


def driving_landmarks(seed: int = 0, n: int = 6) -> np.ndarray:
    """(n, 68, 2) synthetic landmarks near the training faces: jittered, scaled, rotated, moved."""
    rng = np.random.default_rng(seed)
    lm = synthetic_model()[1]
    out = []
    for i in range(n):
        p = lm[i % len(lm)].astype(np.float64) + rng.normal(0, 0.7, (68, 2))
        c = p.mean(0)
        a, s = rng.uniform(-0.15, 0.15), rng.uniform(0.8, 1.4)
        rot = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        out.append((p - c) @ rot.T + c + rng.uniform(-20, 20, 2))
    return np.stack(out).astype(np.float32)


def real_linear_synthesizer(seq, rows: np.ndarray) -> Synthesizer:
    """A linear SADM synthesizer fitted on ``rows`` of a real clip (40 appearance components)."""
    from facesynth.regressors import LinearRegressor

    model = FaceModel.fit(seq, FaceModelConfig(n_appearance=40), rows=rows, progress=False)
    tex = model.sample_textures(seq, rows)
    reg = LinearRegressor.fit(model.shape_params(seq.landmarks[rows], clamp=True), model.appearance_params(tex), {"ridge": 0.0})
    return Synthesizer(model, GlobalAppearance(model, reg)).eval()



def linear_avatar(seq, train: np.ndarray, step: int = 3) -> tuple[Synthesizer, dict]:
    """A small linear model of a real clip (every ``step``-th of its ``train`` rows; default
    face model) and its avatar metadata (neutral, shape PCA, frame), for reenactment tests."""
    from facesynth.onnx.avatar import avatar_metadata

    rows = train[::step]
    model = FaceModel.fit(seq, rows=rows, progress=False)
    x = model.shape_params(seq.landmarks[rows], clamp=True)
    y = model.appearance_params(model.sample_textures(seq, rows), clamp=True)
    syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
    return syn, avatar_metadata(syn, seq.landmarks[train], train, seq)


def assert_export_matches(path, syn: Synthesizer, lm: np.ndarray, tol: float = 1e-4) -> float:
    """Run the ONNX file ``path`` (one thread) and ``syn`` in torch on (B, 68, 2) ``lm``:
    crops equal within ``tol`` where both masks are set, masks equal but for float-rounding
    flips at the outline, placements within 1e-3. Returns the largest crop difference."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    crop, mask, place = sess.run(None, {"landmarks": lm})
    with torch.no_grad():
        t_crop, t_mask, t_place = (t.numpy() for t in syn(torch.from_numpy(lm)))
    assert crop.shape == t_crop.shape and mask.shape == t_mask.shape and place.shape == (len(lm), 2, 3)
    assert (mask != t_mask).mean() < 1e-3
    diff = float(np.abs((crop - t_crop) * mask * t_mask).max())
    assert diff <= tol
    np.testing.assert_allclose(place, t_place, atol=1e-3)
    return diff


def synthetic_talking_head(directory: Path) -> Path:
    """A talking-head file of the built-in synthetic subject (``facesynth train``'s default data:
    40 frames of 128 px, a linear SADM of 8 appearance components, its first 30 frames for
    training), exported once per directory: a real, good file (its neutral face renders at
    about 35 dB against its own frame) for the tests of what a talking head is; ~5 s."""
    from facesynth.data import temporal_split
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.onnx.avatar import avatar_metadata
    from facesynth.onnx.talking_head import export_talking_head

    path = Path(directory) / "synthetic_head.onnx"
    if not path.is_file():
        seq = make_synthetic_sequence(n_frames=40, size=128, seed=0)
        train, _ = temporal_split(len(seq))
        model = FaceModel.fit(seq, FaceModelConfig(n_appearance=8), rows=train, progress=False)
        x = model.shape_params(seq.landmarks[train], clamp=True)
        y = model.appearance_params(model.sample_textures(seq, train), clamp=True)
        syn = Synthesizer(model, GlobalAppearance(model, REGISTRY["linear"].fit(x, y, seed=0))).eval()
        export_talking_head(syn, avatar_metadata(syn, seq.landmarks[train], train, seq), path)
    return path
