"""Transfer pipeline, rasteriser, pose smoothing and the transfer3d command."""

import json

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from facesynth.cli import main
from facesynth.errors import FacesynthError
from facesynth.mesh.camera import MESH_TO_CAMERA, default_intrinsics, project, projection_matrix, rotation_angle_deg
from facesynth.mesh.io import FaceMesh
from facesynth.mesh.preview import expression_stats, pick_sheet_frames
from facesynth.mesh.render import rasterize, shade
from facesynth.mesh.smoothing import PoseFilter
from facesynth.mesh.transfer import Transfer, TransferConfig, umeyama_2d


def _cap_mesh():
    """Front half of an ellipsoid (open mesh, y up, +z to viewer), ~10 cm wide."""
    s = trimesh.creation.icosphere(subdivisions=3)
    V = np.asarray(s.vertices) * [6.0, 8.0, 5.0]
    keep = V[:, 2] > -1.0
    F = s.faces[keep[s.faces].all(axis=1)]
    used = np.unique(F)
    remap = -np.ones(len(V), np.int64)
    remap[used] = np.arange(len(used))
    return FaceMesh(V[used], remap[F])


def _map(mesh, rng):
    front = np.flatnonzero(mesh.vertices[:, 2] > 3.0)
    return rng.choice(front, 68, replace=False)


def _landmarks(mesh, lmap, R, t, K):
    return project(projection_matrix(K, R, t), mesh.vertices[lmap]).astype(np.float32)


def test_umeyama_recovers_similarity(rng):
    src = rng.normal(size=(20, 2))
    th = 0.4
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    s, R2, t = umeyama_2d(src, 1.7 * src @ R.T + [3.0, -2.0])
    assert s == pytest.approx(1.7)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t, [3, -2], atol=1e-12)


@pytest.mark.parametrize("movement", ["transformation", "projection"])
def test_transfer_zero_movement_returns_rest_mesh_and_true_pose(movement, rng):
    mesh = _cap_mesh()
    lmap = _map(mesh, rng)
    K = default_intrinsics(480, 480)
    R = MESH_TO_CAMERA @ Rotation.from_euler("YXZ", [10, -5, 3], degrees=True).as_matrix()
    t = np.array([1.0, 0.5, 50.0])
    Q = _landmarks(mesh, lmap, R, t, K)
    tr = Transfer(mesh, lmap, (480, 480), TransferConfig(movement=movement))
    tr.set_reference(Q)
    # the same face under another head pose: no expression change -> rest mesh
    R2 = MESH_TO_CAMERA @ Rotation.from_euler("YXZ", [-15, 8, -4], degrees=True).as_matrix()
    t2 = np.array([-2.0, 1.0, 60.0])
    out = tr.frame(_landmarks(mesh, lmap, R2, t2, K).astype(float))
    assert rotation_angle_deg(out.pose.R, R2) < 1e-3
    if movement == "projection":
        np.testing.assert_allclose(out.vertices, mesh.vertices, atol=1e-3)
    else:  # the 2D similarity cannot undo out-of-plane rotation exactly: small residual
        assert np.abs(out.vertices - mesh.vertices).max() < 1.0
    same = tr.frame(Q.astype(float))
    np.testing.assert_allclose(same.vertices, mesh.vertices, atol=1e-4)


def test_transfer_moves_handles_in_image_plane_at_constant_depth(rng):
    mesh = _cap_mesh()
    lmap = _map(mesh, rng)
    K = default_intrinsics(480, 480)
    R, t = MESH_TO_CAMERA, np.array([0.0, 0.0, 50.0])
    Q0 = _landmarks(mesh, lmap, R, t, K).astype(float)
    tr = Transfer(mesh, lmap, (480, 480), TransferConfig(movement="projection", anchors="none"))
    tr.set_reference(Q0)
    Q = Q0.copy()
    lips = np.array([57, 58, 56, 66])
    Q[lips, 1] += 6.0  # move a few points 6 px down in the image
    out = tr.frame(Q)
    moved = out.vertices[lmap[lips]]
    Xc = moved @ out.pose.R.T + out.pose.t
    Xc0 = mesh.vertices[lmap[lips]] @ out.pose.R.T + out.pose.t
    np.testing.assert_allclose(Xc[:, 2], Xc0[:, 2], atol=1e-6)  # z kept
    np.testing.assert_allclose(project(projection_matrix(K, np.eye(3), np.zeros(3)), Xc), Q[lips], atol=0.2)


def test_rasterizer_matches_opencv_fill_and_z_order():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    far = np.array([[-0.3, -0.3, 1.0], [0.3, -0.3, 1.0], [0.3, 0.3, 1.0], [-0.3, 0.3, 1.0]])
    near = far * [0.5, 0.5, 1] + [0.1, 0.1, -0.5]
    V = np.vstack([far, near])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    pix, _, _ = rasterize(far, F[:2], K, 100, 100)
    mask = np.zeros((100, 100), np.uint8)
    cv2.fillPoly(mask, [np.round(project(projection_matrix(K, np.eye(3), np.zeros(3)), far)).astype(np.int32)], 1)
    ours = np.zeros(100 * 100, np.uint8)
    ours[pix] = 1
    iou = (ours.reshape(100, 100) & mask).sum() / (ours.reshape(100, 100) | mask).sum()
    assert iou > 0.95
    pix, tri, bary = rasterize(V, F, K, 100, 100)
    np.testing.assert_allclose(bary.sum(axis=1), 1)
    centre = 60 * 100 + 60  # covered by both squares: the near one wins
    assert tri[np.searchsorted(pix, centre)][0] == 4
    img = shade(V, F, K, 100, 100)
    assert img.shape == (100, 100, 3) and img[60, 60].mean() > img[2, 2].mean()


def test_pose_filter_smooths_jitter_and_follows_steps(rng):
    f = PoseFilter(min_cutoff=1.0, beta_t=0.0, beta_r=0.0)
    R0 = MESH_TO_CAMERA
    raw, out = [], []
    for k in range(120):
        R = R0 @ Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix()
        tt = np.array([0, 0, 50.0]) + rng.normal(0, 0.2, 3) + (k >= 60) * np.array([5.0, 0, 0])
        Rs, ts = f(R, tt, k / 30)
        np.testing.assert_allclose(Rs @ Rs.T, np.eye(3), atol=1e-10)
        raw.append((rotation_angle_deg(R, R0), tt))
        out.append((rotation_angle_deg(Rs, R0), ts))
    jit_raw = np.std([r[1][1] for r in raw[10:60]])
    jit_out = np.std([o[1][1] for o in out[10:60]])
    assert jit_out < 0.5 * jit_raw
    assert np.mean([o[0] for o in out[10:60]]) < np.mean([r[0] for r in raw[10:60]])
    assert abs(out[-1][1][0] - 5.0) < 0.5  # the step is followed
    g = PoseFilter()
    Rc, tc = g(R0, np.zeros(3), 0.0)
    for k in range(1, 5):
        Rc, tc = g(R0, np.zeros(3), k / 30)
    np.testing.assert_allclose(Rc, R0, atol=1e-12)


def test_sheet_picks_expression_extremes(rng):
    lm = np.tile(rng.uniform(100, 300, (1, 68, 2)), (10, 1, 1)).astype(np.float32)
    lm[:, 36], lm[:, 45] = [150, 150], [250, 150]
    lm[4, 66] += [0, 30]  # lower inner lip drops in frame 4
    s = expression_stats(lm)
    assert np.argmax(s["mouth_open"]) == 4
    assert dict(pick_sheet_frames(lm, 0))[4] == "jaw open"


def _write_case(tmp_path, rng, n_frames=6):
    mesh = _cap_mesh()
    lmap = _map(mesh, rng)
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(tmp_path / "cap.obj")
    (tmp_path / "map.json").write_text(json.dumps({"map": {str(i + 1): int(v) for i, v in enumerate(lmap)}}))
    K = default_intrinsics(320, 240)
    lm = []
    for k in range(n_frames):
        R = MESH_TO_CAMERA @ Rotation.from_euler("YXZ", [3 * k, 0, 0], degrees=True).as_matrix()
        lm.append(_landmarks(mesh, lmap, R, np.array([0, 0, 60.0]), K))
    lm = np.array(lm)
    lm[2] = np.nan
    np.save(tmp_path / "lm.npy", lm)
    return mesh, lmap


def test_cli_writes_sequence_and_skips_nan_frames(tmp_path, rng, capsys):
    mesh, lmap = _write_case(tmp_path, rng)
    rc = main(["transfer3d", "--mesh", str(tmp_path / "cap.obj"), "--landmark-map", str(tmp_path / "map.json"),
               "--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "seq.npz"),
               "--render", str(tmp_path / "p.mp4"), "--contact-sheet", str(tmp_path / "sheet.png"), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["skipped_nan_frames"] == 1 and summary["frames"] == 5
    z = np.load(tmp_path / "seq.npz")
    assert z["vertices"].shape == (5, len(mesh.vertices), 3)
    assert list(z["frame_index"]) == [0, 1, 3, 4, 5] and list(z["skipped_frames"]) == [2]
    np.testing.assert_array_equal(z["faces"], mesh.faces)
    assert z["R"].shape == (5, 3, 3) and z["K"].shape == (5, 3, 3)
    np.testing.assert_allclose(z["vertices"][0], mesh.vertices, atol=1e-4)
    cap = cv2.VideoCapture(str(tmp_path / "p.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    assert cv2.imread(str(tmp_path / "sheet.png")) is not None


def test_cli_errors(tmp_path, rng, capsys):
    mesh, lmap = _write_case(tmp_path, rng)
    (tmp_path / "bad.json").write_text(json.dumps({"map": {"1": len(mesh.vertices) + 5}}))
    args = ["transfer3d", "--mesh", str(tmp_path / "cap.obj"), "--landmark-map", str(tmp_path / "bad.json"),
            "--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "o.npz")]
    assert main(args) == 2
    assert "exceeds the mesh" in capsys.readouterr().err
    (tmp_path / "nm.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 1 1 1\nf 1 2 3\nf 1 2 4\nf 1 2 5\n")
    args[2] = str(tmp_path / "nm.obj")
    assert main(args) == 2
    assert "non-manifold" in capsys.readouterr().err
    assert not (tmp_path / "o.npz").exists()


def test_transfer_on_real_clip_moves_the_jaw(shared_mesh, shared_clip_dir):
    from facesynth.data import load_landmarks
    from facesynth.mesh.io import load_landmark_map, load_mesh

    mesh = load_mesh(shared_mesh / "ict_face_9409_neutral.obj")
    lmap = load_landmark_map(shared_mesh / "ict_face_9409_ibug68_map.json", len(mesh.vertices))
    lm = load_landmarks(shared_clip_dir("lp_d6"))
    tr = Transfer(mesh, lmap, (480, 480))
    tr.set_reference(lm[0])
    k = int(np.argmax(expression_stats(lm)["mouth_open"]))
    out = tr.frame(lm[k])
    chin, upper = lmap[8], lmap[51]
    drop = (mesh.vertices[chin, 1] - out.vertices[chin, 1]) - (mesh.vertices[upper, 1] - out.vertices[upper, 1])
    assert drop > 1.0  # cm: the chin drops against the upper lip when the mouth opens wide
    np.testing.assert_array_equal(out.vertices[tr.handles], out.targets)


def test_cli_on_real_clip_with_video(shared_mesh, shared_clip_dir, tmp_path, capsys):
    clip = shared_clip_dir("lp_d6")
    rc = main(["transfer3d", "--mesh", str(shared_mesh / "ict_face_9409_neutral.obj"),
               "--landmark-map", str(shared_mesh / "ict_face_9409_ibug68_map.json"), "--landmarks", str(clip),
               "--out", str(tmp_path / "s.npz"), "--stride", "200", "--render", str(tmp_path / "p.mp4"),
               "--contact-sheet", str(tmp_path / "c.png")])
    assert rc == 0
    z = np.load(tmp_path / "s.npz")
    assert z["vertices"].shape == (6, 9409, 3) and z["uvs"].shape == (9409, 2)
    assert list(z["frame_index"]) == [0, 200, 400, 600, 800, 1000]
    meta = json.loads(str(z["meta"]))
    assert meta["summary"]["pose_reprojection_px_mean"] < 10
    cap = cv2.VideoCapture(str(tmp_path / "p.mp4"))
    ok, first = cap.read()
    assert ok and first.shape == (480, 3 * 480, 3)
    sheet = cv2.imread(str(tmp_path / "c.png"))
    assert sheet is not None and sheet.shape[1] >= 3 * 300


def test_cli_preview_uses_frames_of_an_npz(tmp_path, rng):
    _write_case(tmp_path, rng)
    lm = np.load(tmp_path / "lm.npy")
    frames = np.zeros((len(lm), 240, 320, 3), np.uint8)
    frames[..., 2] = 220  # blue frames (RGB)
    np.savez(tmp_path / "seq.npz", landmarks=lm, frames=frames, fps=np.float32(25))
    rc = main(["transfer3d", "--mesh", str(tmp_path / "cap.obj"), "--landmark-map", str(tmp_path / "map.json"),
               "--landmarks", str(tmp_path / "seq.npz"), "--out", str(tmp_path / "o.npz"), "--render", str(tmp_path / "p.mp4")])
    assert rc == 0
    cap = cv2.VideoCapture(str(tmp_path / "p.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(25)
    ok, bgr = cap.read()
    assert ok and bgr.shape == (240, 960, 3)
    corner = bgr[5:40, 5:40].reshape(-1, 3).mean(axis=0)  # video panel: blue (BGR order)
    assert corner[0] > 150 and corner[2] < 60


def test_transfer_with_partial_landmark_map(rng):
    mesh = _cap_mesh()
    lmap = _map(mesh, rng).astype(np.int64)
    lmap[[0, 16, 60, 64]] = -1  # e.g. a mesh without outline ends and inner mouth corners
    K = default_intrinsics(480, 480)
    full = np.where(lmap >= 0, lmap, 0)
    Q = _landmarks(mesh, full, MESH_TO_CAMERA, np.array([0, 0, 50.0]), K).astype(float)
    tr = Transfer(mesh, lmap, (480, 480))
    assert len(tr.handles) == 64
    tr.set_reference(Q)
    Q2 = Q.copy()
    Q2[57, 1] += 5
    out = tr.frame(Q2)
    assert np.isfinite(out.vertices).all()
    assert out.vertices[lmap[57], 1] < mesh.vertices[lmap[57], 1]  # moved down in the image = down in y
    with pytest.raises(FacesynthError, match="mouth corners"):
        bad = lmap.copy()
        bad[48] = -1
        Transfer(mesh, bad, (480, 480))


def test_cli_image_size_option(tmp_path, rng, capsys):
    _write_case(tmp_path, rng)
    base = ["transfer3d", "--mesh", str(tmp_path / "cap.obj"), "--landmark-map", str(tmp_path / "map.json"),
            "--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "o.npz")]
    assert main(base + ["--image-size", "320x240"]) == 0
    z = np.load(tmp_path / "o.npz")
    np.testing.assert_allclose(z["K"][0], default_intrinsics(320, 240))
    assert main(base + ["--image-size", "big"]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
