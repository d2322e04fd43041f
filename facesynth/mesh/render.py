"""A small vectorised z-buffer rasteriser (numpy, no display) for shaded mesh previews.

Every triangle's pixel bounding box is expanded into candidate pixels at once, tested with
barycentric edge functions, and the nearest fragment per pixel is kept by sorting on
(pixel, depth). Pixel centres are at integer (u, v) as in :mod:`facesynth.mesh.camera`;
depth is interpolated perspective-correctly (1/z). Shading is two-sided Lambert with
Phong-interpolated vertex normals and a light near the camera.
"""

from __future__ import annotations

import numpy as np

from facesynth.mesh.camera import MESH_TO_CAMERA, to_camera
from facesynth.mesh.laplacian import vertex_normals

_LIGHT = np.array([-0.35, -0.45, -1.0]) / np.linalg.norm([-0.35, -0.45, -1.0])  # towards the light, camera frame


def rasterize(Vc: np.ndarray, F: np.ndarray, K: np.ndarray, width: int, height: int):
    """Visible triangle and barycentrics per covered pixel.

    Parameters
    ----------
    Vc : (N, 3) camera-frame vertices (z forward); F : (T, 3); K : (3, 3).

    Returns
    -------
    pix : int (P,) flat pixel indices ``v * width + u`` of covered pixels (unique)
    tri : int (P,) the visible triangle at each
    bary : float (P, 3) perspective-correct barycentric weights
    """
    z = Vc[:, 2]
    p = Vc @ K.T
    uv = p[:, :2] / np.where(np.abs(p[:, 2:3]) < 1e-12, 1e-12, p[:, 2:3])
    F = F[(z[F] > 1e-6).all(axis=1)]
    a, b, c = uv[F[:, 0]], uv[F[:, 1]], uv[F[:, 2]]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tri_uv = np.stack([a, b, c], axis=1)
    lo = np.ceil(tri_uv.min(axis=1)).astype(np.int64)
    hi = np.floor(tri_uv.max(axis=1)).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [width - 1, height - 1])
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    keep = (nx > 0) & (ny > 0) & (np.abs(area) > 1e-12)
    F, a, b, c, area, lo, nx, ny = F[keep], a[keep], b[keep], c[keep], area[keep], lo[keep], nx[keep], ny[keep]
    count = nx * ny
    t = np.repeat(np.arange(len(F)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    px = lo[t, 0] + local % nx[t]
    py = lo[t, 1] + local // nx[t]
    # edge functions -> screen-space barycentrics
    w0 = ((b[t, 0] - px) * (c[t, 1] - py) - (b[t, 1] - py) * (c[t, 0] - px)) / area[t]
    w1 = ((c[t, 0] - px) * (a[t, 1] - py) - (c[t, 1] - py) * (a[t, 0] - px)) / area[t]
    w2 = 1.0 - w0 - w1
    inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
    t, px, py, w = t[inside], px[inside], py[inside], np.column_stack([w0, w1, w2])[inside]
    iz = w / z[F[t]]  # perspective-correct: interpolate 1/z
    depth = 1.0 / iz.sum(axis=1)
    bary = iz * depth[:, None]
    pix = py * width + px
    order = np.lexsort((depth, pix))
    pix, first = np.unique(pix[order], return_index=True)
    sel = order[first]
    return pix, F[t[sel]], bary[sel]


def shade(Vc: np.ndarray, F: np.ndarray, K: np.ndarray, width: int, height: int,
          color=(205, 180, 160), background=None, alpha: float = 1.0) -> np.ndarray:
    """Shaded render (height, width, 3) uint8 of camera-frame vertices Vc (N, 3).

    ``background`` (H, W, 3) uint8 is blended under the mesh with opacity ``alpha``;
    without it the background is dark grey.
    """
    img = np.full((height * width, 3), 40, np.float32) if background is None else \
        background.reshape(-1, 3).astype(np.float32).copy()
    pix, tri, bary = rasterize(Vc, F, K, width, height)
    if len(pix):
        n = vertex_normals(Vc, F)
        nn = np.einsum("pk,pkj->pj", bary, n[tri])
        nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)
        lam = np.abs(nn @ _LIGHT)  # two-sided
        val = (0.18 + 0.82 * lam)[:, None] * np.asarray(color, np.float32)[None]
        img[pix] = (1 - alpha) * img[pix] + alpha * val
    return np.clip(img, 0, 255).astype(np.uint8).reshape(height, width, 3)


def render_posed(V: np.ndarray, F: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                 width: int, height: int, **kw) -> np.ndarray:
    """Render mesh-frame vertices V (N, 3) under pose ``X_c = R V + t`` and intrinsics K."""
    return shade(to_camera(R, t, V), F, K, width, height, **kw)


def render_frontal(V: np.ndarray, F: np.ndarray, size: int = 480, fill: float = 0.85, ref: np.ndarray | None = None,
                   **kw) -> np.ndarray:
    """Frontal, upright render (size, size, 3) of mesh-frame vertices V, framed on the
    bounding box of ``ref`` (default V) so that a sequence keeps one framing."""
    ref = V if ref is None else ref
    c = (ref.min(axis=0) + ref.max(axis=0)) / 2
    extent = np.ptp(ref[:, :2], axis=0).max()
    dist = 6.0 * extent
    f = fill * size * dist / extent
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    t = -MESH_TO_CAMERA @ c + np.array([0, 0, dist])
    return render_posed(V, F, MESH_TO_CAMERA, t, K, size, size, **kw)
