"""Mesh sequences <-> geometry videos for the codec route of ``transfer3d`` outputs.

A ``transfer3d`` output (.npz with ``vertices`` (T, V, 3), ``faces`` (F, 3), ``uvs`` (V, 2))
becomes a uint16 geometry video over the mesh's UV layout (:mod:`facesynth.codec.geometry`);
the quantiser's box travels in the stream header, and the topology (faces, uvs, image size)
in a small sidecar ``STREAM.layout.npz`` so that ``codec decode --mesh`` can give the mesh
sequence back (least-squares vertices from the decoded images, ``vertex_solver``).

The codec never imports the mesh wing: the .npz is read as plain arrays.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facesynth.codec.geometry import Quantiser, build_layout, geometry_video, vertex_solver
from facesynth.errors import FacesynthError
from facesynth.io import atomic_path

LAYOUT_SUFFIX = ".layout.npz"


def is_mesh_sequence(path: str | os.PathLike) -> bool:
    """True for an .npz (a ``transfer3d`` output is one)."""
    return str(path).endswith(".npz")


def load_mesh_sequence(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """``vertices`` (T, V, 3) float64, ``faces`` (F, 3) int64, ``uvs`` (V, 2) float64 of an .npz."""
    p = Path(path)
    if not p.is_file():
        raise FacesynthError(f"{p}: file not found")
    try:
        z = np.load(p, allow_pickle=False)
        d = {"vertices": np.asarray(z["vertices"], np.float64), "faces": np.asarray(z["faces"], np.int64),
             "uvs": np.asarray(z["uvs"], np.float64)}
    except KeyError as exc:
        raise FacesynthError(f"{p}: expected a mesh sequence with arrays vertices, faces, uvs "
                             f"(a transfer3d output); missing {exc}") from None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error here
        raise FacesynthError(f"{p}: not a readable .npz ({exc})") from None
    v, f, uv = d["vertices"], d["faces"], d["uvs"]
    if v.ndim != 3 or v.shape[-1] != 3 or len(v) == 0:
        raise FacesynthError(f"{p}: vertices must be (T, V, 3) with T >= 1, got {v.shape}")
    if uv.shape != (v.shape[1], 2):
        raise FacesynthError(f"{p}: uvs must be ({v.shape[1]}, 2) per-vertex UVs (the mesh needs UVs), got {uv.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.min() < 0 or f.max() >= v.shape[1]:
        raise FacesynthError(f"{p}: faces must be (F, 3) indices into the {v.shape[1]} vertices")
    return d


def mesh_to_video(seq: dict[str, np.ndarray], size: int) -> tuple[np.ndarray, np.ndarray, Quantiser]:
    """Mesh sequence -> uint16 geometry video (T, size, size, 3), its mask (size, size) and quantiser."""
    layout = build_layout(seq["faces"], seq["uvs"], size)
    video, q = geometry_video(layout, seq["vertices"])
    return video, layout.mask, q


def write_layout(stream_path: str | os.PathLike, seq: dict[str, np.ndarray], size: int) -> Path:
    """The sidecar ``STREAM.layout.npz``: faces, uvs and image size (what decoding to a mesh needs)."""
    out = Path(str(stream_path) + LAYOUT_SUFFIX)
    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, faces=seq["faces"].astype(np.int32), uvs=seq["uvs"].astype(np.float32), size=np.int64(size))
    return out


def read_layout(path: str | os.PathLike) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FacesynthError(f"{p}: layout sidecar not found (written by 'codec encode' from a mesh sequence; "
                             "give --layout PATH)")
    z = np.load(p, allow_pickle=False)
    return {"faces": z["faces"].astype(np.int64), "uvs": z["uvs"].astype(np.float64), "size": int(z["size"])}


def video_to_mesh(video: np.ndarray, layout: dict, bbox: np.ndarray | None) -> np.ndarray:
    """Decoded uint16 geometry video (T, H, W, 3) -> vertices (T, V, 3) float64 (least squares)."""
    if bbox is None or not np.isfinite(bbox).all():
        raise FacesynthError("stream has no quantiser box: it was not encoded from a mesh sequence")
    if video.shape[1:3] != (layout["size"], layout["size"]):
        raise FacesynthError(f"layout size {layout['size']} does not match the stream's {video.shape[1:3]}")
    lay = build_layout(layout["faces"], layout["uvs"], layout["size"])
    q = Quantiser(np.asarray(bbox[0], np.float64), np.asarray(bbox[1], np.float64))
    return vertex_solver(lay)(q.dequantise(video))
