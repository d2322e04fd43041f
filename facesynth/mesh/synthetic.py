"""A synthetic face-like scan with iBUG-68 landmark vertices and no UVs, for tests that must
run without the shared data: a regular grid over ``[-5, 5] x [-6, 6]`` (mesh units, y up,
+z towards the viewer) shaped as a dome, with the eye (iBUG 37-48) and mouth (49-68)
landmarks at the vertices nearest to ellipses around the eye and mouth centres.
"""

from __future__ import annotations

import numpy as np

EYE_CENTRES = ((-1.7, 1.5), (1.7, 1.5))  # the subject's right eye first (at -x)
MOUTH_CENTRE = (0.0, -2.8)


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.linspace(-5, 5, n), np.linspace(-6, 6, int(round(n * 1.2)))
    X, Y = np.meshgrid(xs, ys)
    ny, nx = X.shape
    a = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return np.stack([X.ravel(), Y.ravel()], 1), F.astype(np.int64)


def _ellipse(c, rx, ry, n, phase=0.0):
    t = np.pi - 2 * np.pi * np.arange(n) / n + phase  # clockwise from the left, as iBUG contours
    return np.stack([c[0] + rx * np.cos(t), c[1] + ry * np.sin(t)], 1)


def synthetic_face(n: int = 41, mouth_open: float = 0.0, dome: float = 3.0, bend: float | None = None
                   ) -> dict[str, np.ndarray]:
    """One synthetic face.

    Parameters
    ----------
    n : grid columns (rows: 1.2 n).
    mouth_open : in [0, 1]; lowers the chin region and hollows the mouth (an expression).
    dome : height of the dome; 0 gives a flat sheet.
    bend : if given, the flat sheet rolled onto a cylinder of this radius about the y axis
        (an exact isometry: geodesic distances are unchanged, Euclidean ones shrink).

    Returns
    -------
    dict ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64 (normals towards +z),
    ``landmarks`` (68,) int64 vertex ids (jaw, brows and nose at the nearest vertices to a
    coarse layout; eyes and mouth as described in the module docstring).
    """
    xy, F = _grid(n)
    x, y = xy[:, 0], xy[:, 1]
    g = lambda cx, cy, sx, sy: np.exp(-((x - cx) ** 2 / (2 * sx**2) + (y - cy) ** 2 / (2 * sy**2)))  # noqa: E731
    z = dome * np.exp(-(x**2 / 40.0 + y**2 / 60.0))
    z = z - 0.3 * dome / 3.0 * (g(*EYE_CENTRES[0], 0.8, 0.5) + g(*EYE_CENTRES[1], 0.8, 0.5))
    yy = y - mouth_open * 0.6 * np.clip((MOUTH_CENTRE[1] - y) / 3.0, 0, 1) * (y < MOUTH_CENTRE[1])
    z = z - mouth_open * 0.5 * g(*MOUTH_CENTRE, 1.0, 0.5)
    V = np.stack([x, yy, z], 1)
    if bend is not None:
        V = np.stack([bend * np.sin(x / bend), y, bend * np.cos(x / bend) - bend], 1)
    pts = np.concatenate([
        np.stack([np.linspace(-4.2, 4.2, 17), -2.0 - 2.5 * np.sin(np.linspace(0, np.pi, 17))], 1),  # jaw
        np.stack([np.linspace(-3.2, -0.6, 5), np.full(5, 2.6)], 1), np.stack([np.linspace(0.6, 3.2, 5), np.full(5, 2.6)], 1),
        np.stack([np.zeros(4), np.linspace(1.2, -0.6, 4)], 1), np.stack([np.linspace(-0.8, 0.8, 5), np.full(5, -1.0)], 1),
        _ellipse(EYE_CENTRES[0], 0.9, 0.45, 6), _ellipse(EYE_CENTRES[1], 0.9, 0.45, 6),
        _ellipse(MOUTH_CENTRE, 1.6, 0.7, 12), _ellipse(MOUTH_CENTRE, 1.1, 0.35, 8),
    ])
    lm = np.array([int(np.argmin(np.linalg.norm(xy - p, axis=1))) for p in pts], np.int64)
    return {"vertices": V, "faces": F, "landmarks": lm}


def synthetic_face_sequence(n: int = 41, n_frames: int = 4) -> dict[str, np.ndarray]:
    """Frames with the mouth opening from 0 to 1: ``frames`` (T, V, 3), ``faces``, ``landmarks``."""
    ts = np.linspace(0.0, 1.0, n_frames)
    faces = [synthetic_face(n, float(t)) for t in ts]
    return {"frames": np.stack([f["vertices"] for f in faces]), "faces": faces[0]["faces"],
            "landmarks": faces[0]["landmarks"]}
