import numpy as np
import pytest

from facesynth.codec.geometry import (
    PEAK16,
    Quantiser,
    build_layout,
    fill_outside,
    geometry_video,
    rasterise,
    sample_vertices,
    vertex_solver,
)
from facesynth.codec.sources import height_field_mesh, ict_blendshape_sequence
from facesynth.errors import FacesynthError
from facesynth.metrics import psnr


def _affine_mesh(n=9):
    m = height_field_mesh(n)
    uv = m["uv"]
    frames = np.stack([3 * uv[:, 0] + 1, -2 * uv[:, 1] + 0.5, 0.7 * uv[:, 0] - 1.3 * uv[:, 1] + 2], 1)
    return frames, m["faces"], uv


def test_rasterise_affine_field_matches_closed_form():
    v, faces, uv = _affine_mesh()
    lay = build_layout(faces, uv, (48, 40))
    img = rasterise(lay, v)
    jj, ii = np.meshgrid(np.arange(40), np.arange(48))
    u, vv = (jj + 0.5) / 40, 1 - (ii + 0.5) / 48
    ref = np.stack([3 * u + 1, -2 * vv + 0.5, 0.7 * u - 1.3 * vv + 2], -1)
    assert lay.mask.all()  # the grid covers the whole unit square
    np.testing.assert_allclose(img, ref, atol=1e-9)


def test_sample_back_recovers_affine_vertices_exactly_and_curved_closely():
    v, faces, uv = _affine_mesh()
    lay = build_layout(faces, uv, 64)
    np.testing.assert_allclose(sample_vertices(lay, rasterise(lay, v)), v, atol=1e-9)
    m = height_field_mesh(41, n_frames=2)
    lay = build_layout(m["faces"], m["uv"], 128)
    rec = sample_vertices(lay, rasterise(lay, m["frames"]))
    assert rec.shape == m["frames"].shape
    assert np.abs(rec - m["frames"]).max() < 0.05  # heights span ~4 units; resampling error
    # the least-squares inverse of the (linear) rasteriser is much closer
    ls = vertex_solver(lay)(rasterise(lay, m["frames"]))
    assert np.abs(ls - m["frames"]).max() < 0.1 * np.abs(rec - m["frames"]).max()


def test_partial_chart_mask_and_ring():
    m = height_field_mesh(11)
    keep = m["uv"][m["faces"]].mean(1)[:, 0] < 0.5  # left half of the square only
    lay = build_layout(m["faces"][keep], m["uv"], 32)
    cols = np.nonzero(lay.mask.any(0))[0]
    assert cols.min() == 0 and 15 <= cols.max() <= 17  # chart + one-pixel ring
    img = rasterise(lay, m["frames"][0])
    assert (img[~lay.mask] == 0).all()


def test_quantiser_psnr_equals_vertex_psnr_relative_to_diagonal(rng):
    pts = rng.normal(size=(500, 3)) * [3, 2, 1]
    q = Quantiser.from_points(pts)
    img = pts.reshape(20, 25, 3)
    noisy = q.quantise(img).astype(np.int64) + rng.integers(-40, 41, img.shape)
    noisy = np.clip(noisy, 0, PEAK16)
    a = psnr(q.quantise(img), noisy, peak=PEAK16)
    err = q.dequantise(noisy) - q.dequantise(q.quantise(img))
    b = 20 * np.log10(q.diag / np.sqrt((err**2).mean()))
    assert a == pytest.approx(b, abs=1e-9)
    np.testing.assert_allclose(q.dequantise(q.quantise(img)), img, atol=q.diag / PEAK16)


def test_fill_outside_keeps_mask_and_is_smooth(rng):
    h = w = 64
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([np.sin(xx / 9.0), np.cos(yy / 7.0), xx * yy / 4000.0], -1)
    mask = (xx - 30) ** 2 + (yy - 34) ** 2 < 20**2
    f = fill_outside(np.where(mask[..., None], img, 1e6), mask)
    np.testing.assert_array_equal(f[mask], img[mask])
    assert f.min() >= img[mask].min() - 1e-9 and f.max() <= img[mask].max() + 1e-9
    lap = np.abs(f[1:-1, 1:-1] * 4 - f[:-2, 1:-1] - f[2:, 1:-1] - f[1:-1, :-2] - f[1:-1, 2:])
    assert lap[~mask[1:-1, 1:-1]].max() < 0.2  # values range over ~2 units


def test_bad_inputs_are_named():
    with pytest.raises(FacesynthError, match="faces"):
        build_layout(np.zeros((3, 4), int), np.zeros((5, 2)), 8)
    with pytest.raises(FacesynthError, match="uv"):
        build_layout(np.array([[0, 1, 2]]), np.array([[0, 0], [2, 0], [0, 1.0]]), 8)
    v, faces, uv = _affine_mesh()
    lay = build_layout(faces, uv, 16)
    with pytest.raises(FacesynthError, match="vertices"):
        rasterise(lay, v[:-1])


@pytest.mark.shared
def test_ict_geometry_video_round_trip(shared_mesh):
    s = ict_blendshape_sequence(shared_mesh, 3)
    lay = build_layout(s["faces"], s["uv"], 256)
    vid, q = geometry_video(lay, s["frames"])
    assert vid.shape == (3, 256, 256, 3) and vid.dtype == np.uint16
    rec = sample_vertices(lay, q.dequantise(vid))
    err = np.linalg.norm(rec - s["frames"], axis=-1)
    assert err.mean() < 0.05  # cm, on a ~40 cm bounding-box diagonal
    assert np.median(err) < 0.01
    ls = np.linalg.norm(vertex_solver(lay)(q.dequantise(vid)) - s["frames"], axis=-1)
    assert ls.mean() < 0.6 * err.mean() and ls.max() < 0.6 * err.max()
