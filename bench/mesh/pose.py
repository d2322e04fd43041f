"""The thesis pose experiment: 50 random cameras look at 18 landmarks of the ICT face mesh;
Gaussian pixel noise sigma in {0, 1, 3, 10}; every pose method (the project's DLT,
normalised DLT and EPnP; OpenCV's EPNP, SQPNP and ITERATIVE) is scored.

    python -m bench.mesh.pose [--cameras 50] [--draws 1] [--markdown T.md] [--json T.json]

Prints ONE JSON line. Per method and sigma: mean and std over trials of

- ``reproj_px``: mean distance of the 18 re-projected points from their noise-free
  positions (the accuracy of the estimated camera, in pixels);
- ``reproj_obs_px``: the same against the noisy observations (what the solver fits);
- ``rot_deg``: geodesic angle between estimated and true rotation;
- ``trans_cm``: ``|t_est - t_true|`` (cm, mesh units), and ``trans_rel`` = that / |t_true|;
- ``focal_rel``: ``|f_est / f - 1|`` (0 for the PnP methods, which are given K);
- ``ms``: solve time.

With 18 points spanning ~10 cm of depth at 40-90 cm, focal length and distance trade off
almost freely, so the DLT methods re-project well while their K, R, t are poorly
determined.

The DLT methods estimate their own intrinsics (11 DOF); the PnP methods are given the
true K. Cameras: image 640x480, f ~ U(800, 1400) px, principal point at the centre
+- 10 px, head yaw ~ U(-30, 30), pitch ~ U(-20, 20), roll ~ U(-10, 10) degrees, distance
~ U(40, 90) cm, lateral offset ~ U(-4, 4) cm; all 18 points lie inside the image.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bench.harness import emit
from facesynth.data.shared import shared_mesh_dir  # noqa: E402
from facesynth.io import write_json, write_text  # noqa: E402
from facesynth.mesh.camera import MESH_TO_CAMERA, project, projection_matrix, rotation_angle_deg  # noqa: E402
from facesynth.mesh.io import load_landmark_map, load_mesh  # noqa: E402
from facesynth.mesh.pose import METHODS, solve_pose  # noqa: E402
from facesynth.mesh.transfer import POSE_LANDMARKS  # noqa: E402
from facesynth.provenance import package_versions  # noqa: E402

#: 18 iBUG landmarks: the 17 rigid pose landmarks and the chin (8).
BENCH_LANDMARKS = np.sort(np.append(POSE_LANDMARKS, 8))
SIGMAS = (0.0, 1.0, 3.0, 10.0)


def random_camera(rng: np.random.Generator, X: np.ndarray, size=(640, 480)):
    """K, R, t with every point of X (N, 3) projecting inside the image."""
    w, h = size
    while True:
        f = rng.uniform(800, 1400)
        K = np.array([[f, 0, (w - 1) / 2 + rng.uniform(-10, 10)], [0, f, (h - 1) / 2 + rng.uniform(-10, 10)], [0, 0, 1]])
        ang = [rng.uniform(-30, 30), rng.uniform(-20, 20), rng.uniform(-10, 10)]
        R = MESH_TO_CAMERA @ Rotation.from_euler("YXZ", ang, degrees=True).as_matrix()
        t = np.array([rng.uniform(-4, 4), rng.uniform(-4, 4), rng.uniform(40, 90)]) - R @ X.mean(axis=0)
        x = project(projection_matrix(K, R, t), X)
        if (x >= 0).all() and (x[:, 0] < w).all() and (x[:, 1] < h).all():
            return K, R, t


def run(args) -> dict:
    mesh_dir = Path(args.mesh_dir) if args.mesh_dir else shared_mesh_dir()
    if mesh_dir is None:
        raise SystemExit("bench_pose: ../shared/data/mesh is absent")
    mesh = load_mesh(mesh_dir / "ict_face_9409_neutral.obj")
    lmap = load_landmark_map(mesh_dir / "ict_face_9409_ibug68_map.json", len(mesh.vertices))
    X = mesh.vertices[lmap[BENCH_LANDMARKS]]
    rng = np.random.default_rng(args.seed)
    cams = [random_camera(rng, X) for _ in range(args.cameras)]
    res: dict = {}
    for sigma in SIGMAS:
        noise_rng = np.random.default_rng([args.seed, int(sigma * 10)])
        obs = []
        for K, R, t in cams:
            x_true = project(projection_matrix(K, R, t), X)
            for _ in range(args.draws):
                obs.append((K, R, t, x_true, x_true + noise_rng.normal(0, sigma, x_true.shape)))
        for method in METHODS:
            rows = []
            for K, R, t, x_true, x in obs:
                t0 = time.perf_counter()
                p = solve_pose(X, x, K, method)
                ms = 1e3 * (time.perf_counter() - t0)
                xe = project(p.P, X)
                rows.append([np.linalg.norm(xe - x_true, axis=1).mean(), np.linalg.norm(xe - x, axis=1).mean(),
                             rotation_angle_deg(p.R, R), np.linalg.norm(p.t - t), np.linalg.norm(p.t - t) / np.linalg.norm(t),
                             abs(p.K[0, 0] / K[0, 0] - 1), ms])
            a = np.array(rows)
            names = ("reproj_px", "reproj_obs_px", "rot_deg", "trans_cm", "trans_rel", "focal_rel", "ms")
            res.setdefault(method, {})[f"{sigma:g}"] = {
                n: {"mean": float(a[:, i].mean()), "std": float(a[:, i].std())} for i, n in enumerate(names)
            }
    return {
        "bench": "pose", "cameras": args.cameras, "draws": args.draws, "trials_per_sigma": args.cameras * args.draws,
        "landmarks_ibug0": BENCH_LANDMARKS.tolist(), "seed": args.seed, "results": res,
    }


def smoothing(args) -> dict:
    """Pose of a real clip per frame (EPnP, 17 rigid landmarks), raw and One Euro smoothed:
    median frame-to-frame rotation change (jitter) and largest deviation of the smoothed
    from the raw rotation (lag on real motion)."""
    from facesynth.data import load_landmarks
    from facesynth.data.shared import shared_clip
    from facesynth.mesh.camera import default_intrinsics
    from facesynth.mesh.smoothing import PoseFilter

    path = shared_clip(args.clip)
    if path is None:
        return {}
    mesh_dir = shared_mesh_dir()
    mesh = load_mesh(mesh_dir / "ict_face_9409_neutral.obj")
    lmap = load_landmark_map(mesh_dir / "ict_face_9409_ibug68_map.json", len(mesh.vertices))
    meta = json.loads((path / "meta.json").read_text())["video"]
    K = default_intrinsics(meta["width"], meta["height"])
    lm = load_landmarks(path)
    X = mesh.vertices[lmap[POSE_LANDMARKS]]
    f = PoseFilter()
    raw, smooth = [], []
    for i, q in enumerate(lm):
        if not np.isfinite(q).all():
            continue
        p = solve_pose(X, q[POSE_LANDMARKS], K, "epnp")
        raw.append((p.R, p.t))
        smooth.append(f(p.R, p.t, i / meta["fps"]))
    step = lambda seq: np.median([rotation_angle_deg(a[0], b[0]) for a, b in zip(seq[:-1], seq[1:], strict=True)])  # noqa: E731
    tstep = lambda seq: np.median([np.linalg.norm(a[1] - b[1]) for a, b in zip(seq[:-1], seq[1:], strict=True)])  # noqa: E731
    dev = [rotation_angle_deg(a[0], b[0]) for a, b in zip(raw, smooth, strict=True)]
    return {"clip": args.clip, "frames": len(raw), "rot_step_deg_median_raw": float(step(raw)),
            "rot_step_deg_median_smoothed": float(step(smooth)), "trans_step_cm_median_raw": float(tstep(raw)),
            "trans_step_cm_median_smoothed": float(tstep(smooth)), "smoothed_vs_raw_deg_p95": float(np.percentile(dev, 95)),
            "smoothed_vs_raw_deg_max": float(np.max(dev))}


def markdown(out: dict) -> str:
    lines = [
        f"Pose methods on {out['cameras']} random cameras x {out['draws']} noise draws, "
        f"{len(out['landmarks_ibug0'])} ICT landmarks (mean +- std; reprojection against the noise-free points).",
        "",
        "| method | sigma px | reproj px | rot deg | trans cm | trans % | focal err % | ms |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for method, by_sigma in out["results"].items():
        for sigma, m in by_sigma.items():
            def f(k, d=2, m=m):
                return f"{m[k]['mean']:.{d}f} +- {m[k]['std']:.{d}f}"
            lines.append(f"| {method} | {sigma} | {f('reproj_px')} | {f('rot_deg')} | {f('trans_cm')} | "
                         f"{100 * m['trans_rel']['mean']:.2f} +- {100 * m['trans_rel']['std']:.2f} | "
                         f"{100 * m['focal_rel']['mean']:.1f} | {m['ms']['mean']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=50)
    ap.add_argument("--draws", type=int, default=1, help="noise draws per camera and sigma")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mesh-dir", default=None, help="folder with the ICT mesh and map (default: shared data)")
    ap.add_argument("--json", default=None, help="also write the full results here")
    ap.add_argument("--markdown", default=None, help="write the table as Markdown here")
    ap.add_argument("--clip", default=None, help="also measure pose jitter with/without One Euro smoothing on this shared clip")
    args = ap.parse_args()
    out = run(args)
    if args.clip:
        out["smoothing"] = smoothing(args)
    out["packages"] = package_versions()
    if args.json:
        write_json(args.json, out)
    if args.markdown:
        write_text(args.markdown, markdown(out))
    emit(out)
if __name__ == "__main__":
    main()
