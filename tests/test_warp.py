"""The tensor piecewise-affine warps against an independent per-triangle OpenCV warp,
and round trips through the reference frame."""

import cv2
import numpy as np
import pytest
import torch
from _faces import face_template, smooth_image

from facesynth.metrics import psnr
from facesynth.model.reference import ReferenceFrame
from facesynth.model.warp import ToReference, ToTarget, apply_affine_t, candidate_spans, invert_affine_t, similarity_to


@pytest.fixture(scope="module")
def ref():
    return ReferenceFrame.from_mean_shape(face_template(), width=96)


def _deformed(ref, rng, amount=3.0):
    """A smooth (fold-free) deformation of the reference shape: low-frequency sinusoids."""
    p = ref.points.astype(np.float64)
    k = rng.uniform(0.02, 0.05, 2)
    ph = rng.uniform(0, 2 * np.pi, 2)
    d = amount * np.stack([np.sin(k[0] * p[:, 1] + ph[0]), np.sin(k[1] * p[:, 0] + ph[1])], -1)
    out = (p + d).astype(np.float32)
    e = out[ref.triangles]
    e1, e2 = e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]
    assert (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0).all(), "deformation folded a triangle"
    return out


def _opencv_piecewise(src_img, src_pts, dst_pts, triangles, out_size):
    """Per-triangle affine warp with OpenCV; returns image and per-pixel triangle id map."""
    h, w = out_size
    out = np.zeros((h, w, src_img.shape[2]), np.float32)
    ids = np.full((h, w), -1, np.int64)
    for t, tri in enumerate(triangles):
        m = cv2.getAffineTransform(dst_pts[tri].astype(np.float32), src_pts[tri].astype(np.float32))
        warped = cv2.warpAffine(src_img, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
        # pixels whose centre lies strictly inside the triangle (1 px away from its edges)
        mask = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(mask, np.round(dst_pts[tri] * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
        mask = cv2.erode(mask, np.ones((3, 3), np.uint8))
        out[mask > 0] = warped[mask > 0]
        ids[mask > 0] = t
    return out, ids


def test_to_reference_matches_opencv(ref, rng):
    img = smooth_image(200, 220)
    target = (ref.points * 1.3 + [30, 15] + rng.normal(0, 2, ref.points.shape)).astype(np.float32)
    sampler = ToReference(ref)
    with torch.no_grad():
        tex = sampler(torch.from_numpy(img).permute(2, 0, 1)[None], torch.from_numpy(target)[None])
    ours = sampler.to_image(tex)[0].permute(1, 2, 0).numpy()
    cv, ids = _opencv_piecewise(img, target, ref.points, ref.triangles, ref.size)
    inside = ids >= 0
    assert inside.sum() > 0.5 * sampler.n_pixels
    # OpenCV's bilinear weights are quantised to 1/32 px; the image is smooth, so this bounds the gap
    assert np.abs(ours[inside] - cv[inside]).max() < 3e-3


def test_to_target_matches_opencv_and_covers_the_face(ref, rng):
    tex_img = smooth_image(*ref.size, seed=3)
    sampler = ToReference(ref)
    tex = torch.from_numpy(tex_img).permute(2, 0, 1).reshape(1, 3, -1)[:, :, sampler.mask_index]
    target = _deformed(ref, rng)
    render = ToTarget(ref, candidate_spans(ref, target[None]))
    with torch.no_grad():
        img, mask = render(tex, torch.from_numpy(target)[None])
    ours = img[0].permute(1, 2, 0).numpy()
    # the target warp extends the texture beyond the mask with nearest-pixel values; give OpenCV the same
    filled = tex[0].T.numpy()[render.fill_index.numpy()].reshape(*ref.size, 3)
    cv, ids = _opencv_piecewise(filled, ref.points, target, ref.triangles, ref.size)
    inside = ids >= 0
    assert np.abs(ours[inside] - cv[inside]).max() < 3e-3
    # the coverage mask equals the triangulated region of the target (brute-force reference)
    from facesynth.model.reference import locate

    ys, xs = np.mgrid[0 : ref.size[0], 0 : ref.size[1]]
    tri_index, _ = locate(np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64), target.astype(np.float64), ref.triangles, eps=1e-5)
    np.testing.assert_array_equal(mask[0, 0].numpy().reshape(-1) > 0, tri_index >= 0)
    assert not render.clipped_triangles(torch.from_numpy(target)[None]).any()


def test_to_target_box_and_onnx_on_a_larger_canvas(ref, rng, tmp_path):
    """Faces anywhere on a canvas larger than the reference, one partly outside it: the
    coverage equals the brute-force triangle test, batches (one box for all) equal single
    frames, and the exported graph (its box is computed per call) equals torch."""
    import onnxruntime as ort

    from facesynth.model.reference import locate

    canvas = (ref.size[0] + 40, ref.size[1] + 70)
    shifts = [(5.37, 3.21), (60.13, 35.71), (-25.29, 10.43)]  # the last one crosses the left edge
    targets = np.stack([_deformed(ref, rng) + np.float32(s) for s in shifts]).astype(np.float32)
    render = ToTarget(ref, candidate_spans(ref, targets), canvas=canvas)
    tex = torch.rand(3, 3, render.n_mask, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        img, mask = render(tex, torch.from_numpy(targets))
    ys, xs = np.mgrid[0 : canvas[0], 0 : canvas[1]]
    pix = np.stack([xs, ys], -1).reshape(-1, 2).astype(np.float64)
    for i, t in enumerate(targets):
        tri_index, _ = locate(pix, t.astype(np.float64), ref.triangles, eps=1e-5)
        np.testing.assert_array_equal(mask[i, 0].numpy().reshape(-1) > 0, tri_index >= 0)
        assert (img[i].numpy()[:, mask[i, 0].numpy() == 0] == 0).all()
        with torch.no_grad():
            one, _ = render(tex[i : i + 1], torch.from_numpy(targets[i : i + 1]))
        torch.testing.assert_close(one, img[i : i + 1], atol=1e-5, rtol=0)
    path = tmp_path / "to_target.onnx"
    with torch.no_grad():
        torch.onnx.export(render, (tex[:2], torch.from_numpy(targets[:2])), str(path), input_names=["tex", "target"],
                          output_names=["img", "mask"], dynamic_axes={"tex": {0: "b"}, "target": {0: "b"}},
                          opset_version=18, dynamo=False)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for rows in ([0, 1, 2], [2], [1]):  # boxes other than the traced one
        got_img, got_mask = sess.run(None, {"tex": tex[rows].numpy(), "target": targets[rows]})
        np.testing.assert_array_equal(got_mask, mask[rows].numpy())
        assert np.abs(got_img - img[rows].numpy()).max() < 1e-4


def test_batched_equals_single(ref, rng):
    sampler = ToReference(ref)
    tex = torch.rand(4, 3, sampler.n_pixels, generator=torch.Generator().manual_seed(0))
    targets = np.stack([_deformed(ref, rng) for _ in range(4)])
    render = ToTarget(ref, candidate_spans(ref, targets))
    with torch.no_grad():
        batch, _ = render(tex, torch.from_numpy(targets))
        for i in range(4):
            one, _ = render(tex[i : i + 1], torch.from_numpy(targets[i : i + 1]))
            torch.testing.assert_close(batch[i : i + 1], one)


def test_frame_without_face_renders_empty(ref, rng):
    """A NaN landmark row (no face) renders empty and leaves the other rows unchanged."""
    targets = np.stack([_deformed(ref, rng), np.full_like(ref.points, np.nan)])
    render = ToTarget(ref, candidate_spans(ref, targets[:1]))
    tex = torch.rand(2, 3, render.n_mask, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        img, mask = render(tex, torch.from_numpy(targets))
        one, one_mask = render(tex[:1], torch.from_numpy(targets[:1]))
    assert not mask[1].any() and not img[1].isnan().any() and not img[1].any()
    torch.testing.assert_close(img[:1], one, atol=1e-5, rtol=0)
    assert torch.equal(mask[:1], one_mask)


def test_round_trip_image_reference_image(ref):
    """image -> reference -> the same shape recovers the face (two bilinear resamplings)."""
    img = smooth_image(160, 150, seed=5)
    sampler = ToReference(ref)
    x = torch.from_numpy(img).permute(2, 0, 1)[None]
    pts = torch.from_numpy(ref.points)[None]
    render = ToTarget(ref, candidate_spans(ref, ref.points[None]), canvas=(160, 150))
    with torch.no_grad():
        back, mask = render(sampler(x, pts), pts)
    m = mask[0, 0].numpy() > 0
    assert m.sum() == sampler.n_pixels  # the same pixels, the same triangles
    assert psnr(back[0].permute(1, 2, 0).numpy(), img, m, peak=1.0) > 50  # identity geometry: exact up to fp


def test_round_trip_through_a_scaled_face(ref):
    """A face at 1.5x the reference scale: frame -> reference -> frame within 35 dB (smooth image)."""
    img = smooth_image(260, 240, seed=7)
    frame_pts = (ref.points * 1.5 + [8, 6]).astype(np.float32)
    sampler = ToReference(ref)
    with torch.no_grad():
        tex = sampler(torch.from_numpy(img).permute(2, 0, 1)[None], torch.from_numpy(frame_pts)[None])
    render = ToTarget(ref, candidate_spans(ref, frame_pts[None]), canvas=(260, 240))
    with torch.no_grad():
        back, mask = render(tex, torch.from_numpy(frame_pts)[None])
    m = cv2.erode((mask[0, 0].numpy() > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert psnr(back[0].permute(1, 2, 0).numpy(), img, m, peak=1.0) > 35


def test_torch_similarity_matches_numpy(rng):
    from facesynth.geometry import similarity_fit

    src = rng.normal(size=(3, 68, 2)) * 20
    dst = rng.normal(size=(68, 2)) * 5
    m_t = similarity_to(torch.from_numpy(src), torch.from_numpy(dst)).numpy()
    np.testing.assert_allclose(m_t, similarity_fit(src, dst[None]), atol=1e-9)
    back = apply_affine_t(apply_affine_t(torch.from_numpy(src), torch.from_numpy(m_t)), invert_affine_t(torch.from_numpy(m_t)))
    np.testing.assert_allclose(back.numpy(), src, atol=1e-9)


def test_a_span_margin_keeps_a_small_triangle_that_moves_a_few_pixels(ref):
    """A small triangle (an eye's: a few pixels wide) widened by 3 px beyond the shapes the
    spans were sized on: the factor alone (1.3 of ~10 px) misses it and leaves columns
    uncovered (clipped_triangles); a margin in pixels covers it, and the spans are the factor's
    plus the margin."""
    p = ref.points.astype(np.float64)
    tri = ref.triangles
    width = np.ptp(p[tri][:, :, 0], axis=1)
    t = int(np.argmin(np.where(width > 4, width, np.inf)))  # the narrowest real triangle
    target = p.copy()
    right = tri[t][np.argmax(p[tri[t], 0])]
    target[right, 0] += 0.5 * width[t] + 3.0  # its rightmost vertex moved out: wider by half + 3 px
    plain, margin = candidate_spans(ref, p[None]), candidate_spans(ref, p[None], margin=6)
    np.testing.assert_array_equal(margin, plain + 6)
    t_target = torch.from_numpy(target[None].astype(np.float32))
    assert ToTarget(ref, plain).clipped_triangles(t_target)[0, t]
    assert not ToTarget(ref, margin).clipped_triangles(t_target)[0].any()
