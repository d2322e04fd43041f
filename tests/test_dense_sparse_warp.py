"""``model.warp_points=sparse`` on the 478-point scheme: the warp's vertices are the iBUG-68
view plus the eye and lip contours (Delaunay), the other points regressor inputs only; it
trains, exports and matches torch in ONNX Runtime."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from _dense import dense_sequence
from scipy.spatial import Delaunay

from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.landmarks import IBUG68, MEDIAPIPE478, folded_triangles
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.sadm.fit import fit_sadm, load_sadm, save_sadm

CFG = FaceModelConfig(reference_width=64, appearance_variance=0.95, warp_points="sparse")


@pytest.fixture(scope="module")
def sparse(shared_mesh):
    seq68 = make_synthetic_sequence(n_frames=40, size=160, seed=3)
    seq = dense_sequence(seq68, shared_mesh / "mediapipe_canonical_468_arrays.npz")
    model, tex = FaceModel.fit_with_textures(seq, CFG, progress=False)
    return seq, model, tex


def test_sparse_points_are_the_ibug68_view_and_the_eye_and_lip_contours():
    sub = MEDIAPIPE478.sparse_points()
    read = np.flatnonzero(MEDIAPIPE478.ibug68_matrix().any(0))
    expected = np.union1d(read, np.concatenate([MEDIAPIPE478.region("eyes"), MEDIAPIPE478.region("mouth")]))
    np.testing.assert_array_equal(sub, expected)
    assert not np.isin(MEDIAPIPE478.region("irises"), sub).any()
    np.testing.assert_array_equal(IBUG68.sparse_points(), np.arange(68))


def test_sparse_warp_is_a_delaunay_of_those_points_only(sparse):
    seq, model, _ = sparse
    sub = MEDIAPIPE478.sparse_points()
    for ref in (model.reference,  # the default: the mean's triangles, on its opened mouth
                FaceModel.fit(seq, replace(CFG, reference_mouth_quantile=0.0), progress=False).reference):
        assert ref.points.shape == (478, 2)
        assert set(np.unique(ref.triangles).tolist()) == set(sub.tolist())
        assert not folded_triangles(ref.points, ref.triangles).any()
        assert ref.n_triangles < len(MEDIAPIPE478.triangulation()) / 3
    # on the mean itself, the same triangles as scipy's Delaunay of the reference's points
    independent = sub[Delaunay(ref.points[sub].astype(np.float64)).simplices]
    assert {frozenset(t) for t in ref.triangles.tolist()} == {frozenset(t) for t in independent.tolist()}
    _, mask, _ = model.render(np.repeat(model.appearance_pca.mean[None], 4, 0), seq.landmarks[:4])
    assert mask.sum() > 0


def test_sparse_warp_trains_exports_and_matches_torch(sparse, tmp_path):
    pytest.importorskip("onnx")
    from facesynth.onnx.synthesis import check_export, export_synthesizer

    seq, model, tex = sparse
    save_sadm(fit_sadm(model, seq, np.arange(len(seq)), tex, "linear"), tmp_path / "run")
    loaded = load_sadm(tmp_path / "run")
    np.testing.assert_array_equal(loaded.model.reference.triangles, model.reference.triangles)  # stored, not rebuilt
    assert loaded.model.config.warp_points == "sparse"
    syn = loaded.synthesizer()
    assert syn(torch.from_numpy(seq.landmarks[:2]))[1].sum() > 0
    path = export_synthesizer(syn, tmp_path / "m.onnx")
    assert check_export(syn, path, seq.landmarks[::7] + np.float32(0.3), tol=1e-4) <= 1e-4


def test_unknown_warp_points_is_a_clear_error(sparse):
    seq, _, _ = sparse
    with pytest.raises(FacesynthError, match=r"model\.warp_points must be one of \('mesh', 'sparse'\), got 'dense'"):
        FaceModel.fit(seq, replace(CFG, warp_points="dense"), progress=False)
