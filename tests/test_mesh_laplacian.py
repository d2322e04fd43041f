"""Cotangent Laplacian against closed forms and a per-triangle reference; Laplacian
deformation invariants (zero movement, exact hard handles, soft handles, errors)."""

import numpy as np
import pytest
import scipy.sparse as sp

from facesynth.errors import FacesynthError
from facesynth.mesh.deform import LaplacianDeformer, LaplacianSystem
from facesynth.mesh.io import check_mesh_manifold, load_landmark_map, load_mesh
from facesynth.mesh.laplacian import (
    boundary_vertices,
    cotangent_laplacian,
    distortion,
    face_adjacency,
    uniform_laplacian,
)


def grid(n=6, h=0.7, z=None):
    """(n x n) vertex grid, spacing h, each square split along the same diagonal."""
    ys, xs = np.mgrid[0:n, 0:n]
    V = np.column_stack([xs.ravel() * h, ys.ravel() * h, np.zeros(n * n) if z is None else z(xs, ys).ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return V, F, idx


def test_flat_grid_cotangent_laplacian_is_the_five_point_stencil():
    V, F, idx = grid(7, h=0.3)
    L = cotangent_laplacian(V, F).toarray()
    # closed form: right isosceles triangles have cot 45 = 1 opposite the axis edges and
    # cot 90 = 0 opposite the diagonals, so interior rows are 4 on the diagonal and -1 at
    # the four axis neighbours, independent of the spacing.
    for i in range(1, 6):
        for j in range(1, 6):
            row = np.zeros(49)
            row[idx[i, j]] = 4
            row[[idx[i - 1, j], idx[i + 1, j], idx[i, j - 1], idx[i, j + 1]]] = -1
            np.testing.assert_allclose(L[idx[i, j]], row, atol=1e-12)
    np.testing.assert_allclose(L, L.T, atol=1e-12)
    np.testing.assert_allclose(L.sum(axis=1), 0, atol=1e-12)
    interior = ~boundary_vertices(F, len(V))
    np.testing.assert_allclose((L @ V)[interior], 0, atol=1e-12)  # linear precision


def _reference_cot_laplacian(V, F):
    """Independent per-triangle loop with angles from arccos."""
    n = len(V)
    L = np.zeros((n, n))
    for tri in F:
        for k in range(3):
            i, j, o = tri[(k + 1) % 3], tri[(k + 2) % 3], tri[k]
            u, w = V[i] - V[o], V[j] - V[o]
            ang = np.arccos(u @ w / np.linalg.norm(u) / np.linalg.norm(w))
            c = 0.5 / np.tan(ang)
            L[i, j] -= c
            L[j, i] -= c
            L[i, i] += c
            L[j, j] += c
    return L


def test_cotangent_laplacian_matches_reference_on_curved_mesh(rng):
    V, F, _ = grid(5, z=lambda x, y: 0.3 * np.sin(x) * np.cos(0.7 * y))
    V = V + rng.normal(0, 0.05, V.shape)
    np.testing.assert_allclose(cotangent_laplacian(V, F).toarray(), _reference_cot_laplacian(V, F), atol=1e-10)


def test_uniform_laplacian_of_dual_graph_has_valence_at_most_three():
    _, F, _ = grid(5)
    A = face_adjacency(F)
    deg = np.asarray(A.sum(axis=1)).ravel()
    assert deg.max() == 3 and deg.min() >= 1
    L = uniform_laplacian(A)
    np.testing.assert_allclose(L @ np.ones(len(F)), 0, atol=1e-12)


def _curved_grid(n=12):
    return grid(n, h=1.0, z=lambda x, y: 0.05 * (x - n / 2) ** 2 + 0.03 * (y - n / 2) ** 2)


@pytest.mark.parametrize("method", ["plain", "iterative", "dual"])
def test_zero_movement_returns_input_mesh(method):
    V, F, idx = _curved_grid()
    handles = np.concatenate([idx[0], idx[-1], [idx[6, 6]]])
    d = LaplacianDeformer(V, F, handles, method=method)
    out, info = d.deform(V[handles], return_info=True)
    np.testing.assert_allclose(out, V, atol=1e-7)
    assert info.converged


@pytest.mark.parametrize("method", ["plain", "iterative", "dual"])
def test_hard_handles_land_exactly_on_targets(method, rng):
    V, F, idx = _curved_grid()
    handles = np.concatenate([idx[0], idx[-1], [idx[6, 6]]])
    targets = V[handles] + rng.normal(0, 0.3, (len(handles), 3))
    out = LaplacianDeformer(V, F, handles, method=method).deform(targets)
    assert np.array_equal(out[handles], targets)
    assert np.isfinite(out).all()


def test_hard_solution_is_the_constrained_least_squares_minimum(rng):
    V, F, idx = _curved_grid(8)
    handles = np.array([idx[0, 0], idx[7, 7], idx[0, 7], idx[3, 4]])
    targets = V[handles] + rng.normal(0, 0.5, (4, 3))
    out = LaplacianDeformer(V, F, handles).deform(targets)
    # dense reference: lstsq over the free vertices
    L = cotangent_laplacian(V, F).toarray()
    free = np.setdiff1d(np.arange(len(V)), handles)
    rhs = L @ V - L[:, handles] @ targets
    ref = np.linalg.lstsq(L[:, free], rhs, rcond=None)[0]
    np.testing.assert_allclose(out[free], ref, atol=1e-8)


def test_soft_handles_approach_targets_as_weight_grows(rng):
    V, F, idx = _curved_grid(8)
    handles = np.array([idx[0, 0], idx[7, 7], idx[0, 7], idx[7, 0]])
    targets = V[handles] + rng.normal(0, 0.5, (4, 3))
    errs = [np.abs(LaplacianDeformer(V, F, handles, constraints="soft", weight=w).deform(targets)[handles] - targets).max()
            for w in (0.1, 1.0, 100.0)]
    assert errs[0] > errs[1] > errs[2] and errs[2] < 1e-3
    np.testing.assert_allclose(LaplacianDeformer(V, F, handles, constraints="soft").deform(V[handles]), V, atol=1e-9)


def test_translation_is_reproduced(rng):
    V, F, idx = _curved_grid(8)
    handles = np.array([idx[0, 0], idx[7, 7], idx[3, 5]])
    shift = np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(LaplacianDeformer(V, F, handles).deform(V[handles] + shift), V + shift, atol=1e-9)


def test_distortion_zero_for_rest_and_scale_for_scaled():
    V, F, _ = _curved_grid(6)
    assert distortion(V, V, F)["edge_mean"] == 0
    d = distortion(V, 2 * V, F)
    assert d["edge_mean"] == pytest.approx(1.0) and d["area_mean"] == pytest.approx(3.0)


def test_errors():
    V, F, idx = grid(4)
    with pytest.raises(FacesynthError, match="unknown method"):
        LaplacianDeformer(V, F, [0], method="magic")
    with pytest.raises(FacesynthError, match="handle indices"):
        LaplacianSystem(sp.eye(3), np.array([5]))
    with pytest.raises(FacesynthError, match="targets must be"):
        LaplacianDeformer(V, F, [0, 1]).deform(np.zeros((3, 3)))
    bad = np.vstack([F, F[:1]])  # a triangle twice: edges in 3 faces
    with pytest.raises(FacesynthError, match="non-manifold"):
        check_mesh_manifold(bad, len(V), "x.obj")


def test_map_index_beyond_mesh_and_non_manifold_file(tmp_path):
    (tmp_path / "m.json").write_text('{"map": {"1": 3, "2": 99}}')
    with pytest.raises(FacesynthError, match=r"m\.json.*vertex 99 exceeds the mesh"):
        load_landmark_map(tmp_path / "m.json", 10)
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 1 1\nf 1 2 3\nf 1 2 4\nf 1 2 5\n"
    (tmp_path / "fan.obj").write_text(obj)
    with pytest.raises(FacesynthError, match=r"fan\.obj: non-manifold"):
        load_mesh(tmp_path / "fan.obj")


def test_ict_mesh_loads_in_file_order(shared_mesh):
    m = load_mesh(shared_mesh / "ict_face_9409_neutral.obj")
    z = np.load(shared_mesh / "ict_face_9409_arrays.npz")
    np.testing.assert_allclose(m.vertices, z["vertices"], atol=1e-5)
    assert np.array_equal(m.faces, z["faces"]) and m.uvs.shape == (9409, 2)
    h = load_landmark_map(shared_mesh / "ict_face_9409_ibug68_map.json", len(m.vertices))
    assert (h >= 0).all() and len(np.unique(h)) == 68
