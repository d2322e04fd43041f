"""Hole filling (facesynth.mesh.holes): closed forms on planes and spheres, the ICT face."""

import numpy as np
import pytest

from facesynth.codec.sources import height_field_mesh
from facesynth.errors import FacesynthError
from facesynth.mesh.holes import fill_holes, loop_crease_angles, punch_hole
from facesynth.mesh.io import check_mesh_manifold
from facesynth.mesh.laplacian import ordered_boundary_loops


def _plane(n=25):
    m = height_field_mesh(n)
    V = m["frames"][0].copy()
    V[:, 2] = 0.0
    return V, m["faces"]


def _sphere_cap():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    V, F = np.asarray(s.vertices), np.asarray(s.faces, np.int64)
    keep = (V[F][:, :, 2] > -1.0).all(axis=1)
    F = F[keep]
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def test_ordered_loops_follow_the_half_edges():
    V, F = _plane(9)
    (loop,) = ordered_boundary_loops(F)
    assert len(loop) == 32
    he = {tuple(e) for e in np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).tolist()}
    assert all((a, b) in he for a, b in zip(loop, np.roll(loop, -1), strict=True))
    # outer rim counter-clockwise seen from +z (the faces' normal side): positive signed area
    x, y = V[loop, 0], V[loop, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0


def test_plane_hole_is_filled_flat_and_linear_colours_exactly():
    V, F = _plane()
    center = int(np.argmin(np.linalg.norm(V[:, :2] - [0.3, -0.4], axis=1)))
    V1, F1, _ = punch_hole(V, F, center, 2.2)
    colours = np.stack([0.3 * V1[:, 0] + 0.1 * V1[:, 1] + 2.0, -V1[:, 1]], 1)
    fm = fill_holes(V1, F1, colors=colours)
    assert len(fm.loops) == 1 and fm.vertices.shape[0] > V1.shape[0] + 10
    check_mesh_manifold(fm.faces, len(fm.vertices), "filled")
    assert len(ordered_boundary_loops(fm.faces)) == 1  # only the rim is left open
    new = fm.vertices[fm.n_original:]
    np.testing.assert_allclose(new[:, 2], 0.0, atol=1e-10)
    ref = np.stack([0.3 * new[:, 0] + 0.1 * new[:, 1] + 2.0, -new[:, 1]], 1)
    np.testing.assert_allclose(fm.colors[fm.n_original:], ref, atol=1e-8)  # bi-Laplace reproduces linear
    np.testing.assert_array_equal(fm.vertices[:fm.n_original], V1)  # originals untouched
    # the patch is triangulated at the density of the mesh around it
    e_old = np.linalg.norm(V1[F1[:, 0]] - V1[F1[:, 1]], axis=1).mean()
    Fp = fm.faces[len(F1):]
    e_new = np.linalg.norm(fm.vertices[Fp[:, 0]] - fm.vertices[Fp[:, 1]], axis=1).mean()
    assert 0.6 < e_new / e_old < 1.6
    # no flipped patch triangle (normals all +z)
    n = np.cross(fm.vertices[Fp[:, 1]] - fm.vertices[Fp[:, 0]], fm.vertices[Fp[:, 2]] - fm.vertices[Fp[:, 0]])
    assert (n[:, 2] > 0).all()


@pytest.mark.parametrize("radius", [0.8, 1.6])
def test_sphere_hole_is_refilled_close_to_the_sphere_with_smooth_seam(radius):
    V, F = _sphere_cap()
    top = int(np.argmax(V[:, 2]))
    V1, F1, kept = punch_hole(V, F, top, radius)
    fm = fill_holes(V1, F1)
    new = fm.vertices[fm.n_original:]
    err = np.abs(np.linalg.norm(new, axis=1) - 5.0)
    assert err.max() < 0.02 * 5.0  # thin plate vs sphere: a small sag, measured 0.1-1 % of r
    (loop,) = fm.loops
    seam = loop_crease_angles(fm.vertices, fm.faces, loop)
    ref = loop_crease_angles(V, F, kept[loop])  # the same edges on the unbroken sphere
    assert seam.max() < ref.max() + 3.0 and seam.mean() < 2 * ref.mean() + 1.0


def test_keep_open_and_errors():
    V, F = _plane()
    c1 = int(np.argmin(np.linalg.norm(V[:, :2] - [-2, 2], axis=1)))
    c2 = int(np.argmin(np.linalg.norm(V[:, :2] - [2, -2], axis=1)))
    V1, F1, kept = punch_hole(V, F, c1, 1.2)
    V2, F2, kept2 = punch_hole(V1, F1, int(np.nonzero(kept == c2)[0][0]), 1.2)
    loops = ordered_boundary_loops(F2)
    assert len(loops) == 3
    hole_a = loops[1]
    fm = fill_holes(V2, F2, keep_open=hole_a[:1])
    assert len(fm.loops) == 1 and len(ordered_boundary_loops(fm.faces)) == 2
    with pytest.raises(FacesynthError, match="vertices"):
        fill_holes(V2[:, :2], F2)
    nothing = fill_holes(V, F)
    assert nothing.loops == [] and nothing.vertices.shape == V.shape


@pytest.mark.shared
def test_ict_face_holes(shared_mesh):
    igl = pytest.importorskip("igl")
    d = np.load(shared_mesh / "ict_face_9409_arrays.npz")
    V, F = d["vertices"].astype(float), d["faces"].astype(np.int64)
    rim = np.concatenate(ordered_boundary_loops(F))
    cheek = 1200  # a vertex on the subject's right cheek
    for radius, tol in ((0.5, 0.02), (1.0, 0.03)):  # cm
        V1, F1, kept = punch_hole(V, F, cheek, radius)
        fm = fill_holes(V1, F1, colors=V1, keep_open=np.nonzero(np.isin(kept, rim))[0])
        assert len(fm.loops) == 1
        new = fm.vertices[fm.n_original:]
        d2, _, _ = igl.point_mesh_squared_distance(new, V, F.astype(np.int32))
        assert np.sqrt(d2.mean()) < tol
        np.testing.assert_allclose(fm.colors[fm.n_original:], new, atol=3 * tol)  # colour = position
