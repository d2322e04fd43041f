"""Mesh sequences with fixed topology and UVs, to be turned into geometry videos.

- :func:`ict_blendshape_sequence`: the ICT-FaceKit face (9409 vertices) animated by
  smooth, seeded blendshape weight curves (real geometry, synthetic animation).
- :func:`height_field_mesh`: a synthetic face-like height field on a regular grid, for
  unit tests that must run without the shared data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facesynth.errors import FacesynthError


def load_ict_mesh(mesh_dir: str | Path) -> dict[str, np.ndarray]:
    """Load ``ict_face_9409_arrays.npz`` and the blendshapes from ``mesh_dir``.

    Returns
    -------
    dict with ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64, ``uv`` (V, 2) float64,
    ``blendshapes`` (K, V, 3) float64 (offsets from neutral).
    """
    mesh_dir = Path(mesh_dir)
    arrays = mesh_dir / "ict_face_9409_arrays.npz"
    bs = mesh_dir / "ict_face_9409_blendshapes.npy"
    for p in (arrays, bs):
        if not p.is_file():
            raise FacesynthError(f"{p}: ICT mesh file not found")
    d = np.load(arrays)
    try:
        out = {"vertices": d["vertices"].astype(np.float64), "faces": d["faces"].astype(np.int64),
               "uv": d["uv"].astype(np.float64)}
    except KeyError as exc:
        raise FacesynthError(f"{arrays}: expected arrays vertices, faces, uv ({exc})") from None
    out["blendshapes"] = np.load(bs).astype(np.float64)
    if out["blendshapes"].shape[1:] != out["vertices"].shape:
        raise FacesynthError(f"{bs}: expected (K, {len(out['vertices'])}, 3), got {out['blendshapes'].shape}")
    return out


def blendshape_weights(n_frames: int, n_shapes: int, seed: int = 0, active: int = 8) -> np.ndarray:
    """Smooth weight curves (T, K) in [0, 1]: ``active`` shapes, each a raised sine with
    random period (20-60 frames) and phase; the rest stay at zero."""
    rng = np.random.default_rng(seed)
    w = np.zeros((n_frames, n_shapes))
    t = np.arange(n_frames)[:, None]
    which = rng.choice(n_shapes, size=min(active, n_shapes), replace=False)
    period = rng.uniform(20, 60, len(which))
    phase = rng.uniform(0, 2 * np.pi, len(which))
    amp = rng.uniform(0.4, 1.0, len(which))
    w[:, which] = amp * 0.5 * (1 - np.cos(2 * np.pi * t / period + phase))
    return w


def ict_blendshape_sequence(mesh_dir: str | Path, n_frames: int, seed: int = 0) -> dict[str, np.ndarray]:
    """ICT face animated by :func:`blendshape_weights`: ``frames`` (T, V, 3) plus faces, uv."""
    m = load_ict_mesh(mesh_dir)
    w = blendshape_weights(n_frames, len(m["blendshapes"]), seed)
    frames = m["vertices"][None] + np.einsum("tk,kvc->tvc", w, m["blendshapes"])
    return {"frames": frames, "faces": m["faces"], "uv": m["uv"], "weights": w}


def height_field(u: np.ndarray, v: np.ndarray, t: float = 0.0) -> np.ndarray:
    """Face-like height over the unit square: a dome, a nose ridge, two eye sockets and a
    mouth whose opening grows with ``t`` in [0, 1]."""
    g = lambda cx, cy, sx, sy: np.exp(-((u - cx) ** 2 / (2 * sx**2) + (v - cy) ** 2 / (2 * sy**2)))  # noqa: E731
    z = 3.0 * g(0.5, 0.5, 0.35, 0.45) + 1.2 * g(0.5, 0.5, 0.05, 0.15)
    z -= 0.5 * (g(0.33, 0.62, 0.07, 0.04) + g(0.67, 0.62, 0.07, 0.04))
    z -= (0.2 + 0.6 * t) * g(0.5, 0.25, 0.12, 0.03 + 0.03 * t)
    return z


def height_field_mesh(n: int = 41, n_frames: int = 1) -> dict[str, np.ndarray]:
    """Regular grid mesh of :func:`height_field`: ``frames`` (T, n*n, 3), ``faces``, ``uv``.

    Vertex ``(u, v)`` sits at ``x = 10 u - 5, y = 12 v - 6, z = height_field(u, v, t)``,
    with UV = (u, v) over the whole unit square.
    """
    g = np.linspace(0.0, 1.0, n)
    uu, vv = np.meshgrid(g, g)
    uv = np.stack([uu.ravel(), vv.ravel()], 1)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    ts = np.linspace(0, 1, n_frames) if n_frames > 1 else np.zeros(1)
    frames = np.stack([np.stack([10 * uv[:, 0] - 5, 12 * uv[:, 1] - 6, height_field(uv[:, 0], uv[:, 1], t)], 1)
                       for t in ts])
    return {"frames": frames, "faces": faces, "uv": uv}
