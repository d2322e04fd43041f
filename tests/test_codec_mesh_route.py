"""The route transfer3d -> codec encode -> codec decode --mesh on a short synthetic sequence."""

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from facesynth.cli import main
from facesynth.codec.sources import height_field_mesh
from facesynth.mesh.camera import MESH_TO_CAMERA, default_intrinsics, project, projection_matrix

# vertex error tolerances, as a fraction of the quantiser box diagonal
LOSSLESS_MAX = 2e-4  # 16-bit quantisation + least-squares recovery of vertices between pixel centres (measured 5e-5)
LOSSY_RMS = 5e-4  # --qp 24 (measured 5e-5)


def _case(tmp_path, n_frames=5):
    m = height_field_mesh(n=25)
    verts = m["frames"][0]
    mesh = trimesh.Trimesh(verts, m["faces"], visual=trimesh.visual.TextureVisuals(uv=m["uv"]), process=False)
    mesh.export(tmp_path / "face.obj")
    rng = np.random.default_rng(3)
    inner = np.flatnonzero((np.abs(verts[:, 0]) < 3.5) & (np.abs(verts[:, 1]) < 4.5))
    lmap = rng.choice(inner, 68, replace=False)
    (tmp_path / "map.json").write_text(json.dumps({"map": {str(i + 1): int(v) for i, v in enumerate(lmap)}}))
    K = default_intrinsics(320, 240)
    lm = []
    for k in range(n_frames):
        R = MESH_TO_CAMERA @ Rotation.from_euler("YXZ", [4 * k, 0, 0], degrees=True).as_matrix()
        q = project(projection_matrix(K, R, np.array([0, 0, 60.0])), verts[lmap])
        q[48:68, 1] += 1.5 * k  # the mouth points move down: the mesh deforms
        lm.append(q)
    np.save(tmp_path / "lm.npy", np.asarray(lm, np.float32))


@pytest.mark.parametrize("qp_args, tol", [(["--lossless"], LOSSLESS_MAX), (["--qp", "24"], LOSSY_RMS)])
def test_transfer3d_to_codec_and_back(tmp_path, capsys, qp_args, tol):
    _case(tmp_path)
    assert main(["transfer3d", "--mesh", str(tmp_path / "face.obj"), "--landmark-map", str(tmp_path / "map.json"),
                 "--landmarks", str(tmp_path / "lm.npy"), "--out", str(tmp_path / "seq.npz"), "--image-size", "320x240",
                 "--quiet", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["neutral_rule"].startswith("automatic")
    seq = np.load(tmp_path / "seq.npz")
    assert np.ptp(seq["vertices"], axis=0).max() > 0.05  # frames differ: something to code
    assert main(["codec", "encode", str(tmp_path / "seq.npz"), str(tmp_path / "s.fsgv"), *qp_args, "--size", "64",
                 "--preview", str(tmp_path / "enc.png"), "--quiet", "--json"]) == 0
    enc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (tmp_path / "s.fsgv.layout.npz").is_file() and (tmp_path / "enc.png").stat().st_size > 0
    assert main(["codec", "decode", str(tmp_path / "s.fsgv"), str(tmp_path / "back.npz"), "--mesh",
                 "--preview", str(tmp_path / "dec.png"), "--reference", str(tmp_path / "seq.npz"), "--quiet"]) == 0
    back = np.load(tmp_path / "back.npz")
    np.testing.assert_array_equal(back["faces"], seq["faces"])
    v0, v1 = seq["vertices"].astype(np.float64), back["vertices"].astype(np.float64)
    assert v1.shape == v0.shape
    diag = float(np.linalg.norm(v0.reshape(-1, 3).max(0) - v0.reshape(-1, 3).min(0)))
    err = np.linalg.norm(v1 - v0, axis=-1) / diag
    if qp_args == ["--lossless"]:
        assert enc["psnr_db"] is None  # exact reconstruction of the geometry video
        assert err.max() < tol
    else:
        assert np.sqrt((err**2).mean()) < tol
    assert (tmp_path / "dec.png").stat().st_size > 0


def test_decode_mesh_without_layout_is_a_clear_error(tmp_path, capsys):
    video = np.zeros((1, 16, 16, 3), np.uint16)
    np.save(tmp_path / "v.npy", video)
    assert main(["codec", "encode", str(tmp_path / "v.npy"), str(tmp_path / "v.fsgv"), "--lossless", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["codec", "decode", str(tmp_path / "v.fsgv"), str(tmp_path / "m.npz"), "--mesh"]) == 2
    assert "layout sidecar not found" in capsys.readouterr().err
