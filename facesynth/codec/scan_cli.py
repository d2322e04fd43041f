"""``facesynth codec scan``: a face-scan sequence without UVs -> geometry video.

Where the mesh wing (fill, segment, parameterise: :mod:`facesynth.mesh.scan`) meets the
codec (geometry images: :mod:`facesynth.codec.geometry`); a CLI module, so it may import both.

Inputs: one ``.npz`` with ``vertices`` (T, V, 3) or (V, 3) and ``faces`` (F, 3), or one
OBJ/PLY per frame; landmarks as a JSON iBUG map (``{"map": {"1": vertex, ...}}``) or an
``.npy`` of 68 vertex ids, (68,) for every frame or (T, 68). Outputs: ``OUT.npy`` (uint16
video, encodable by ``facesynth codec encode``), ``OUT.mask.npy`` (pixels covered in every
frame) and ``OUT.scan.npz`` (per frame: ``uv_t``, ``faces_t``, ``source_t``; ``lo``, ``hi``
of the quantiser), from which the vertices are sampled back after decoding.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from facesynth import progress
from facesynth.errors import FacesynthError


def add_arguments(p: argparse.ArgumentParser) -> None:
    from facesynth.mesh.scan import DEFAULT_RADIUS, METHODS
    from facesynth.mesh.segment import SOURCES

    p.add_argument("inputs", type=Path, nargs="+", help="one .npz (vertices, faces) or one OBJ/PLY per frame")
    p.add_argument("output", type=Path, help="uint16 (T, H, W, 3) .npy")
    p.add_argument("--landmarks", type=Path, required=True, help="iBUG-68 vertex map .json, or .npy (68,) / (T, 68)")
    p.add_argument("--size", type=int, default=256, help="geometry image side in pixels (default 256)")
    p.add_argument("--radius", type=float, default=DEFAULT_RADIUS,
                   help="geodesic segmentation radius in mesh units (paper: 60-65 mm male, 45-50 mm female)")
    p.add_argument("--sources", choices=SOURCES, default=SOURCES[0],
                   help="segmentation features: anchored (eye corners + nose, mouth, chin; default), points "
                        "(eyes + mouth, the paper's) or contours")
    p.add_argument("--method", choices=METHODS, default="eip", help="eip (expression-invariant) or hm (disk)")
    p.add_argument("--no-fill", action="store_true", help="do not fill holes first")


def load_sequence(inputs: list[Path]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Frames' vertices and faces from one .npz or a list of mesh files."""
    if len(inputs) == 1 and inputs[0].suffix == ".npz":
        path = inputs[0]
        if not path.is_file():
            raise FacesynthError(f"{path}: file not found")
        d = np.load(path)
        if "vertices" not in d or "faces" not in d:
            raise FacesynthError(f"{path}: expected arrays 'vertices' (T, V, 3) and 'faces' (F, 3)")
        v = np.asarray(d["vertices"], np.float64)
        v = v[None] if v.ndim == 2 else v
        f = np.asarray(d["faces"], np.int64)
        if v.ndim != 3 or v.shape[2] != 3 or f.ndim != 2 or f.shape[1] != 3 or f.max() >= v.shape[1]:
            raise FacesynthError(f"{path}: vertices {v.shape} / faces {f.shape} are not (T, V, 3) / (F, 3) within V")
        return list(v), [f] * len(v)
    from facesynth.mesh.io import load_mesh

    meshes = [load_mesh(p) for p in inputs]
    return [m.vertices for m in meshes], [m.faces for m in meshes]


def load_landmarks(path: Path, n_frames: int, n_vertices: list[int]) -> np.ndarray:
    """(T, 68) int64 landmark vertices."""
    if path.suffix == ".json":
        from facesynth.mesh.io import load_landmark_map

        lm = load_landmark_map(path, min(n_vertices))
    else:
        if not path.is_file():
            raise FacesynthError(f"{path}: file not found")
        lm = np.load(path, allow_pickle=False)
    lm = np.asarray(lm, np.int64)
    lm = np.broadcast_to(lm, (n_frames, 68)) if lm.shape == (68,) else lm
    if lm.shape != (n_frames, 68):
        raise FacesynthError(f"{path}: expected 68 landmark vertices or (T={n_frames}, 68), got {lm.shape}")
    return lm


def scan_geometry_video(vertices: list[np.ndarray], faces: list[np.ndarray], landmarks: np.ndarray, size: int,
                        radius: float | None = None, method: str = "eip", fill: bool = True,
                        sources: str | None = None):
    """Process every frame (:func:`facesynth.mesh.scan.process_scan`) and build the video.

    Returns ``(video uint16 (T, H, W, 3), mask (H, W), quantiser, frames: list of ScanFrame,
    layouts)``."""
    from facesynth.codec.geometry import build_layout, geometry_video_layouts
    from facesynth.mesh.scan import DEFAULT_RADIUS, process_scan

    extra = {} if sources is None else {"sources": sources}
    frames = [process_scan(v, f, lm, DEFAULT_RADIUS if radius is None else radius, method, fill, **extra)
              for v, f, lm in zip(vertices, faces, landmarks, strict=True)]
    layouts = [build_layout(fr.faces, np.clip(fr.uv, 0.0, 1.0), size) for fr in frames]
    video, q, mask = geometry_video_layouts(layouts, [fr.vertices for fr in frames])
    return video, mask, q, frames, layouts


def run(args: argparse.Namespace) -> int:
    from facesynth.io import atomic_path, check_writable, save_npy

    if args.size < 16:
        raise FacesynthError(f"--size: expected >= 16, got {args.size}")
    check_writable(args.output)  # before the work
    verts, faces = load_sequence(args.inputs)
    lm = load_landmarks(args.landmarks, len(verts), [len(v) for v in verts])
    video, mask, q, frames, _ = scan_geometry_video(verts, faces, lm, args.size, args.radius, args.method,
                                                    not args.no_fill, args.sources)
    side = {"lo": q.lo, "hi": q.hi}
    for t, fr in enumerate(frames):
        side[f"uv_{t}"], side[f"faces_{t}"], side[f"source_{t}"] = fr.uv, fr.faces, fr.source
    save_npy(args.output, video)
    save_npy(args.output.with_suffix(".mask.npy"), mask)
    with atomic_path(args.output.with_suffix(".scan.npz")) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **side)
    figures = {"output": str(args.output), "shape": list(video.shape), "method": args.method,
               "mask_share": float(mask.mean()), "vertices": [len(fr.vertices) for fr in frames],
               "holes_filled": [fr.filled for fr in frames], "flipped": [fr.flipped for fr in frames],
               "untangled": [fr.untangled for fr in frames], "diag": q.diag}
    progress.result(f"codec scan: wrote {args.output} ({len(frames)} scans -> shape {list(video.shape)}, "
                    f"{args.method})", figures)
    return 0
