"""The reference frame's slivers spread (facesynth.model.reference.spread_triangles): a band
of a fixed triangulation that most training frames squash, and some open wide, gets enough
reference pixels for the wide ones, by moving the mean shape as little as it takes.

Areas are checked against OpenCV's contourArea, folds against the scheme's orientation rule."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from facesynth.errors import FacesynthError
from facesynth.landmarks import MEDIAPIPE478, folded_triangles, triangle_areas
from facesynth.model.reference import AREA_STRETCH, spread_triangles


def grid(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of points (x, y) 0..n-1 and its triangles, counter-clockwise in image axes."""
    ys, xs = np.mgrid[0:n, 0:n]
    pts = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    tri = []
    for r in range(n - 1):
        for c in range(n - 1):
            i = r * n + c
            tri += [[i, i + 1, i + n], [i + 1, i + n + 1, i + n]]
    tri = np.asarray(tri, np.int64)
    assert (triangle_areas(pts, tri) > 0).all()
    return pts, tri


def band_frames(pts: np.ndarray, n: int, rows: int = 200, seed: int = 0) -> np.ndarray:
    """Frames of the grid whose band between rows 2 and 3 is mostly squashed (height 0.02-0.2)
    and opens to 2 in a tenth of them; the other rows keep unit height with a little jitter."""
    rng = np.random.default_rng(seed)
    height = np.where(rng.random(rows) < 0.1, 2.0, rng.uniform(0.02, 0.2, rows))
    out = np.repeat(pts[None], rows, 0)
    below = out[..., 1] >= 3
    out[..., 1] = np.where(below, out[..., 1] - 1 + height[:, None], out[..., 1])
    return out + rng.normal(0, 0.01, out.shape)


def test_triangle_areas_match_opencv():
    pts, tri = grid(4)
    rng = np.random.default_rng(1)
    shape = pts * 7.3 + rng.normal(0, 0.2, pts.shape)
    got = triangle_areas(shape, tri)
    ref = [cv2.contourArea(shape[t].astype(np.float32)) for t in tri]
    np.testing.assert_allclose(np.abs(got), ref, rtol=1e-5)
    assert (got > 0).all()  # the scheme's orientation: counter-clockwise in image axes
    assert (triangle_areas(shape[None, None], tri) == got).all()  # broadcasts over leading axes


def test_a_squashed_band_is_spread_to_what_its_wide_frames_need():
    n = 5
    pts, tri = grid(n)
    frames = band_frames(pts, n)
    mean = frames.mean(0)
    out, info = spread_triangles(mean, frames, tri, 0.95)
    share = triangle_areas(frames, tri) / np.abs(triangle_areas(frames, tri)).sum(-1, keepdims=True)
    own = triangle_areas(mean, tri)
    want = np.quantile(share, 0.95, 0) * own.sum() / AREA_STRETCH
    band = (np.isin(tri, np.arange(2 * n, 3 * n)).any(1) & np.isin(tri, np.arange(3 * n, 4 * n)).any(1))
    assert info["spread"] and info["short_triangles"] >= band.sum()
    assert (own[band] < 0.5 * want[band]).all()  # the mean squashes the band
    got = triangle_areas(out, tri)
    assert (got[band] >= 0.99 * want[band]).all()  # and now holds what its 95th percentile needs
    assert not folded_triangles(out, tri).any()
    # no other triangle pays for it with its own area (the stretch is not moved to a neighbour)
    assert (got[~band] >= 0.99 * own[~band]).all()


def test_a_shape_with_room_everywhere_is_left_alone_and_a_fold_is_never_made():
    pts, tri = grid(4)
    rng = np.random.default_rng(2)
    frames = pts[None] + rng.normal(0, 0.02, (50, *pts.shape))
    out, info = spread_triangles(pts, frames, tri, 0.9)
    assert not info["spread"] and info["short_triangles"] == 0 and (out == pts).all()
    # a triangle folded on the shape itself is not a target (ReferenceFrame keeps it last)
    folded = pts.copy()
    folded[5] = [0.2, 0.2]  # inside the triangle (0, 1, 4): its neighbours fold
    base = folded_triangles(folded, tri)
    assert base.any()
    out, info = spread_triangles(folded, band_frames(pts, 4), tri, 0.9)
    assert not (folded_triangles(out, tri) & ~base).any()


def test_the_face_model_spreads_a_dense_mesh_and_refuses_a_bad_quantile(shared_mesh):
    from _dense import dense_sequence

    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.model.face_model import FaceModel, FaceModelConfig

    seq = dense_sequence(make_synthetic_sequence(n_frames=24, size=160, seed=3),
                         shared_mesh / "mediapipe_canonical_468_arrays.npz")
    cfg = FaceModelConfig(reference_width=64, n_appearance=4)
    with pytest.raises(FacesynthError, match=r"model\.reference_area_quantile must lie in \[0, 1\] \(0 = off\), got 1\.5"):
        FaceModel.fit(seq, replace(cfg, reference_area_quantile=1.5), progress=False)
    on = FaceModel.fit(seq, cfg, progress=False)
    off = FaceModel.fit(seq, replace(cfg, reference_area_quantile=0.0), progress=False)
    assert off.meta["reference_spread"] == {}
    spread = on.meta["reference_spread"]
    assert spread["spread"] and spread["short_triangles"] >= 1 and spread["largest_shortfall_after"] < 1.01
    fixed = MEDIAPIPE478.triangulation()  # no triangle folded that the mean does not fold
    assert not (folded_triangles(on.reference.points, fixed) & ~folded_triangles(off.reference.points, fixed)).any()
    assert on.reference.points.shape == off.reference.points.shape and (on.reference.points != off.reference.points).any()


def test_the_model_measures_its_stretch_against_opencv(shared_mesh):
    """FaceModel.stretch: 1 on any similarity of the reference shape; a frame with one
    triangle's vertex pulled out gives that triangle's area ratio (OpenCV's contourArea at the
    reference's scale)."""
    from _dense import dense_sequence

    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.model.face_model import FaceModel, FaceModelConfig

    seq = dense_sequence(make_synthetic_sequence(n_frames=12, size=160, seed=4),
                         shared_mesh / "mediapipe_canonical_468_arrays.npz")
    model = FaceModel.fit(seq, FaceModelConfig(reference_width=64, n_appearance=3), progress=False)
    ref = model.reference.points.astype(np.float64)
    c, s = np.cos(0.3), np.sin(0.3)
    moved = ref @ (2.5 * np.array([[c, -s], [s, c]])).T + [40.0, -7.0]
    np.testing.assert_allclose(model.stretch(moved[None].astype(np.float32)), [1.0], rtol=1e-3)
    # the lower lip's middle point (17) pulled 3 px down on the reference: its triangles grow
    pulled = ref.copy()
    pulled[17, 1] += 3.0
    got = float(model.stretch(pulled[None].astype(np.float32))[0])
    tri = model.reference.triangles
    live = triangle_areas(ref, tri) > 0
    canvas = model.to_canvas(pulled[None].astype(np.float32))[0][0]
    ratios = [cv2.contourArea(canvas[t].astype(np.float32)) / cv2.contourArea(ref[t].astype(np.float32))
              for t in tri[live] if 17 in t]
    assert got == pytest.approx(max(ratios), rel=1e-3) and got > 1.5
