"""Loading face meshes (trimesh, vertex order kept) and iBUG-68 landmark vertex maps."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facesynth.errors import FacesynthError
from facesynth.landmarks import N_LANDMARKS


@dataclass
class FaceMesh:
    """A triangle mesh in the mesh frame (y up, +z towards the viewer).

    Attributes
    ----------
    vertices : float64 (V, 3)
    faces : int64 (F, 3)
    uvs : float32 (V, 2) or None (OBJ convention, v up)
    source : str
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    source: str = ""


def load_mesh(path: str | os.PathLike, check_manifold: bool = True) -> FaceMesh:
    """Read a mesh with trimesh (``process=False``, so vertex order is the file's).

    Raises FacesynthError for an unreadable file, a non-triangle/empty mesh, or (with
    ``check_manifold``) a non-manifold one (see :func:`check_manifold`).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FacesynthError(f"{path}: no such mesh file")
    try:
        m = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise FacesynthError(f"{path}: not a readable mesh ({exc})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise FacesynthError(f"{path}: expected a triangle mesh with faces")
    uv = getattr(m.visual, "uv", None)
    mesh = FaceMesh(
        np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64),
        None if uv is None or len(uv) != len(m.vertices) else np.asarray(uv, np.float32), str(path),
    )
    if check_manifold:
        check_mesh_manifold(mesh.faces, len(mesh.vertices), str(path))
    return mesh


def check_mesh_manifold(faces: np.ndarray, n_vertices: int, where: str = "mesh") -> None:
    """Raise FacesynthError unless the mesh is an edge-manifold, consistently oriented
    triangle mesh: every edge in one or two triangles, interior edges used once in each
    direction, no degenerate triangle, every vertex used."""
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3:
        raise FacesynthError(f"{where}: faces must be (F, 3) triangles, got {F.shape}")
    if F.min() < 0 or F.max() >= n_vertices:
        raise FacesynthError(f"{where}: face indices outside 0..{n_vertices - 1}")
    if ((F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])).any():
        raise FacesynthError(f"{where}: non-manifold mesh (degenerate triangle with a repeated vertex)")
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, dcount = np.unique(directed, axis=0, return_counts=True)
    if (dcount > 1).any():
        raise FacesynthError(f"{where}: non-manifold mesh (an edge is used twice in one direction: "
                             "more than two faces on an edge or inconsistent orientation)")
    _, ucount = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    if (ucount > 2).any():
        raise FacesynthError(f"{where}: non-manifold mesh ({int((ucount > 2).sum())} edges in more than two faces)")
    if len(np.unique(F)) != n_vertices:
        raise FacesynthError(f"{where}: {n_vertices - len(np.unique(F))} vertices belong to no face")


def load_landmark_map(path: str | os.PathLike, n_vertices: int) -> np.ndarray:
    """iBUG-68 -> vertex map as int64 (68,), -1 where a landmark is missing.

    The JSON holds ``{"map": {"1": vertex, ..., "68": vertex}, "missing_ibug": [...]}``
    with 1-based iBUG keys (as in .pts files) and 0-based vertex indices.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FacesynthError(f"{path}: not a readable JSON landmark map ({exc})") from None
    mp = doc.get("map") if isinstance(doc, dict) else None
    if not isinstance(mp, dict):
        raise FacesynthError(f"{path}: expected an object with a 'map' of 1-based iBUG keys -> vertex")
    out = np.full(N_LANDMARKS, -1, np.int64)
    for key, v in mp.items():
        try:
            k = int(key)
            v = int(v)
        except (TypeError, ValueError):
            raise FacesynthError(f"{path}: map entry {key!r}: {v!r} is not integer") from None
        if not 1 <= k <= N_LANDMARKS:
            raise FacesynthError(f"{path}: map key {k} outside the 1-based iBUG range 1..{N_LANDMARKS}")
        if not 0 <= v < n_vertices:
            raise FacesynthError(f"{path}: map entry {k} -> vertex {v} exceeds the mesh (0..{n_vertices - 1})")
        out[k - 1] = v
    if (out >= 0).sum() < 6:
        raise FacesynthError(f"{path}: map has {(out >= 0).sum()} landmarks, need at least 6")
    return out
