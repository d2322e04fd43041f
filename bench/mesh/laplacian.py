"""Laplacian deformation: factorisation and per-frame solve time, and (with --clips) the
plain / iterative / dual methods on real clips.

    python -m bench.mesh.laplacian                  # timing, ICT + subdivided ICT
    python -m bench.mesh.laplacian --clips lp_d6 lp_d3 --frames 40   # methods

Prints ONE JSON line. Timing: factorisation (cotangent Laplacian + normal equations +
splu) and the median per-frame plain solve (all three coordinates) for the 9409-vertex
ICT mesh and for the ICT mesh midpoint-subdivided ``--subdiv`` times (>= 50k vertices
with 2). Methods: per clip, frames spread over the clip are transferred with each method;
iterations to converge, time per frame, and edge-length / triangle-area distortion against
the rest mesh (and the distance to the plain solution); the median final relative
change, and how often / after how many iterations it fell below 1e-2.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bench.harness import emit, load_average
from facesynth.data.shared import shared_clip, shared_mesh_dir  # noqa: E402
from facesynth.mesh.deform import LaplacianDeformer  # noqa: E402
from facesynth.mesh.io import load_landmark_map, load_mesh  # noqa: E402
from facesynth.mesh.laplacian import distortion  # noqa: E402


def _targets(V, handles, rng, scale=0.5):
    """Smooth random handle movement (cm): a jaw-drop-like offset plus noise."""
    T = V[handles].copy()
    T[:, 1] -= scale * np.clip(-(T[:, 1] - T[:, 1].max()) / np.ptp(T[:, 1]), 0, 1)
    return T + rng.normal(0, 0.1 * scale, T.shape)


def time_case(V, F, handles, repeats, rng) -> dict:
    t0 = time.perf_counter()
    d = LaplacianDeformer(V, F, handles, method="plain")
    fact = time.perf_counter() - t0
    targets = [_targets(V, handles, rng) for _ in range(repeats)]
    d.deform(targets[0])  # warm-up
    ts = []
    for T in targets:
        t0 = time.perf_counter()
        out = d.deform(T)
        ts.append(time.perf_counter() - t0)
    assert np.array_equal(out[handles], targets[-1])
    lu = d.system.lu
    return {
        "vertices": int(len(V)), "faces": int(len(F)), "handles": int(len(handles)),
        "factorisation_s": round(fact, 4), "solve_ms_median": round(1e3 * float(np.median(ts)), 3),
        "solve_ms_p90": round(1e3 * float(np.percentile(ts, 90)), 3), "solve_ms_min": round(1e3 * float(np.min(ts)), 3),
        "factor_nnz": int(lu.L.nnz + lu.U.nnz),
    }


def timing(args) -> dict:

    import trimesh

    mesh_dir = shared_mesh_dir()
    if mesh_dir is None:
        raise SystemExit("bench_laplacian: ../shared/data/mesh is absent")
    m = load_mesh(mesh_dir / "ict_face_9409_neutral.obj")
    h = load_landmark_map(mesh_dir / "ict_face_9409_ibug68_map.json", len(m.vertices))
    rng = np.random.default_rng(args.seed)
    out = {"load_average_1min": load_average(), "ict": time_case(m.vertices, m.faces, h, args.repeats, rng)}
    V, F = m.vertices, m.faces
    for k in range(args.subdiv):
        V, F = trimesh.remesh.subdivide(V, F)  # original vertices keep their indices
        out[f"ict_subdiv{k + 1}"] = time_case(V, F, h, max(5, args.repeats // 4), rng)
    return out


def methods(args) -> dict:
    from facesynth.data import load_landmarks
    from facesynth.mesh.transfer import Transfer, TransferConfig

    mesh_dir = shared_mesh_dir()
    m = load_mesh(mesh_dir / "ict_face_9409_neutral.obj")
    h = load_landmark_map(mesh_dir / "ict_face_9409_ibug68_map.json", len(m.vertices))
    res = {}
    for clip in args.clips:
        path = shared_clip(clip)
        if path is None:
            continue
        lm = load_landmarks(path)
        meta = json.loads((path / "meta.json").read_text())["video"]
        rows = np.linspace(0, len(lm) - 1, args.frames).round().astype(int)
        plain = None
        res[clip] = {}
        for method in ("plain", "iterative", "dual"):
            tr = Transfer(m, h, (meta["width"], meta["height"]), TransferConfig(method=method, max_iter=args.max_iter, tol=args.tol))
            tr.set_reference(lm[0])
            Vs, its, conv, dist, ts, last, to1e2 = [], [], [], [], [], [], []
            for r in rows:
                t0 = time.perf_counter()
                fr = tr.frame(lm[r])
                ts.append(time.perf_counter() - t0)
                Vs.append(fr.vertices)
                its.append(fr.info.iterations)
                conv.append(fr.info.converged)
                rc = fr.info.rel_change
                last.append(rc[-1] if rc else 0.0)
                to1e2.append(next((i + 2 for i, r in enumerate(rc) if r < 1e-2), fr.info.iterations if not rc else -1))
                dist.append(distortion(m.vertices, fr.vertices, m.faces))
            entry = {
                "frames": len(rows), "iterations_mean": float(np.mean(its)), "iterations_max": int(np.max(its)),
                "converged_fraction": float(np.mean(conv)), "ms_per_frame": round(1e3 * float(np.median(ts)), 2),
                "final_rel_change_median": float(np.median(last)),
                "reached_rel_1e-2_fraction": float(np.mean(np.array(to1e2) > 0)),
                "iterations_to_rel_1e-2_median": float(np.median([x for x in to1e2 if x > 0])) if any(x > 0 for x in to1e2) else None,
            }
            for key in dist[0]:
                entry[key] = float(np.mean([d[key] for d in dist]))
            if plain is None:
                plain = Vs
            else:
                entry["rms_vs_plain_cm"] = float(np.sqrt(np.mean([np.mean((a - b) ** 2) for a, b in zip(Vs, plain, strict=True)])))
            res[clip][method] = entry
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50, help="frames timed on the ICT mesh")
    ap.add_argument("--subdiv", type=int, default=2, help="midpoint subdivisions of ICT for the large case")
    ap.add_argument("--clips", nargs="*", default=[], help="run the methods comparison on these shared clips")
    ap.add_argument("--frames", type=int, default=30, help="frames per clip for the methods comparison")
    ap.add_argument("--max-iter", type=int, default=30)
    ap.add_argument("--tol", type=float, default=1e-3, help="convergence threshold of the iterative methods")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = {"bench": "laplacian", "timing": None if args.clips else timing(args)}
    if args.clips:
        out["methods"] = methods(args)
    emit(out)
if __name__ == "__main__":
    main()
