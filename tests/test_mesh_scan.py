"""Geodesic segmentation, the expression-invariant parameterisation and the scan -> codec
route, on a synthetic face scan (no shared data) and on the ICT face."""

import json

import numpy as np
import pytest

pytest.importorskip("potpourri3d")
pytest.importorskip("igl")

from facesynth.errors import FacesynthError  # noqa: E402
from facesynth.mesh.eip import Domain, harmonic_disk, parameterise, signed_areas  # noqa: E402
from facesynth.mesh.paths import geodesic_distance  # noqa: E402
from facesynth.mesh.scan import process_scan, uv_drift  # noqa: E402
from facesynth.mesh.segment import EYE_L, EYE_R, MOUTH_INNER, feature_distance, segment_face  # noqa: E402
from facesynth.mesh.synthetic import synthetic_face, synthetic_face_sequence  # noqa: E402


@pytest.fixture(scope="module")
def face():
    f = synthetic_face(33)
    return f, segment_face(f["vertices"], f["faces"], f["landmarks"], 3.0)


def _local(region, lm, n):
    loc = np.full(n, -1)
    loc[region.kept] = np.arange(len(region.kept))
    return loc[lm]


def test_heat_geodesics_agree_with_exact_and_the_plane():
    f = synthetic_face(33, dome=0.0)
    V, F = f["vertices"], f["faces"]
    src = [int(f["landmarks"][30])]
    heat, exact = geodesic_distance(V, F, src, "heat"), geodesic_distance(V, F, src, "exact")
    euclid = np.linalg.norm(V - V[src[0]], axis=1)  # on a plane, geodesic = Euclidean
    np.testing.assert_allclose(exact, euclid, atol=1e-9)
    far = euclid > 1.0
    assert np.median(np.abs(heat - exact)[far] / exact[far]) < 0.03
    with pytest.raises(FacesynthError, match="method"):
        geodesic_distance(V, F, src, "nope")


def test_segmentation_has_four_loops_through_the_landmarks(face):
    f, region = face
    assert set(region.loops) == {"outer", "eye_r", "eye_l", "mouth"} and not region.extra_loops
    lm = _local(region, f["landmarks"], len(f["vertices"]))
    V = region.vertices
    edge = np.linalg.norm(V[region.faces[:, 0]] - V[region.faces[:, 1]], axis=1).max()
    for name, ix in (("eye_r", EYE_R), ("eye_l", EYE_L), ("mouth", MOUTH_INNER)):
        loop = V[region.loops[name]]
        gap = np.linalg.norm(V[lm[ix]][:, None] - loop[None], axis=2).min(1)
        assert (gap <= edge).all() and (gap == 0).mean() > 0.6  # the openings follow the contours
    d = feature_distance(f["vertices"], f["faces"], f["landmarks"])
    assert d[region.kept].max() <= 3.0 and len(region.kept) < len(f["vertices"])


def test_geodesic_region_survives_an_isometric_bend_and_the_euclidean_ball_does_not():
    flat, bent = synthetic_face(33, dome=0.0), synthetic_face(33, dome=0.0, bend=2.5)
    change = {}
    for metric in ("geodesic", "euclidean"):  # the paper's sources (eye and mouth points), one radius
        a = set(segment_face(flat["vertices"], flat["faces"], flat["landmarks"], 3.0, metric=metric, sources="points").kept.tolist())
        b = set(segment_face(bent["vertices"], bent["faces"], bent["landmarks"], 3.0, metric=metric, sources="points").kept.tolist())
        change[metric] = len(a ^ b) / len(a)
    assert change["geodesic"] <= 0.01  # measured 0.2 %
    assert change["euclidean"] > 0.01 and change["euclidean"] > 5 * change["geodesic"]  # measured 1.6 %


def test_spots_enclosed_by_the_region_are_kept_and_the_outside_is_not():
    from facesynth.mesh.segment import _close_islands

    f = synthetic_face(21, dome=0.0)
    V, F = f["vertices"], f["faces"]
    c = V[F].mean(axis=1)
    region = F[np.linalg.norm(c[:, :2], axis=1) < 4.0]
    spot = np.linalg.norm(c[:, :2] - [0.5, 0.5], axis=1) < 1.0  # inside the disk
    region_with_hole = F[(np.linalg.norm(c[:, :2], axis=1) < 4.0) & ~spot]
    closed = _close_islands(V, F, region_with_hole)
    assert len(closed) == len(region) and {tuple(t) for t in closed.tolist()} == {tuple(t) for t in region.tolist()}
    assert len(_close_islands(V, F, region)) == len(region)  # nothing enclosed: unchanged


def test_segmentation_errors(face):
    f, _ = face
    with pytest.raises(FacesynthError, match="68"):
        segment_face(f["vertices"], f["faces"], f["landmarks"][:60], 3.0)
    with pytest.raises(FacesynthError, match="radius"):
        segment_face(f["vertices"], f["faces"], f["landmarks"], -1.0)
    with pytest.raises(FacesynthError, match="metric"):
        segment_face(f["vertices"], f["faces"], f["landmarks"], 3.0, metric="manhattan")
    with pytest.raises(FacesynthError, match="sources"):
        segment_face(f["vertices"], f["faces"], f["landmarks"], 3.0, sources="nope")
    no_chin = f["landmarks"].copy()
    no_chin[8] = -1  # the default (anchored) sources need the chin; the paper's points do not
    with pytest.raises(FacesynthError, match="landmark vertices .*9"):
        segment_face(f["vertices"], f["faces"], no_chin, 3.0)
    assert len(segment_face(f["vertices"], f["faces"], no_chin, 3.0, sources="points").kept) > 0


def test_eip_is_bijective_and_puts_loops_on_the_holes(face):
    f, region = face
    lm = _local(region, f["landmarks"], len(f["vertices"]))
    res = parameterise(region.vertices, region.faces, region.loops, lm)
    assert res.flipped == 0 and (signed_areas(res.uv, region.faces) > 0).all()
    uv, dom = res.uv, Domain()
    h = dom.holes()
    cell = 1.0 / dom.grid
    for name in ("eye_r", "eye_l", "mouth"):
        cu, cv, ru, rv = h[name]
        p = uv[region.loops[name]]
        r = np.sqrt(((p[:, 0] - cu) / ru) ** 2 + ((p[:, 1] - cv) / rv) ** 2)
        # on the hole outline: the domain's polygon through points of the ellipse (chord sag < a cell)
        assert np.abs(r - 1).max() * min(ru, rv) < cell
    rim = uv[region.loops["outer"]]
    np.testing.assert_allclose(np.minimum.reduce([rim[:, 0], 1 - rim[:, 0], rim[:, 1], 1 - rim[:, 1]]), 0, atol=1e-9)
    np.testing.assert_allclose(uv[res.c, 1], h["eye_r"][1], atol=1e-9)  # c on the slit c'
    np.testing.assert_allclose(uv[res.d, 0], 0.5, atol=1e-9)  # d on the slit d'
    inner = np.isin(np.arange(len(uv)), np.concatenate([region.loops[k] for k in ("outer", "eye_r", "eye_l", "mouth")]))
    assert (uv[~inner] > 0).all() and (uv[~inner] < 1).all()


def test_domain_stream_function_is_constant_along_traced_gradient_curves():
    import matplotlib.tri as mtri

    ref = Domain().coordinates()
    V, F, loops, *_ = Domain().mesh()
    f = np.zeros(len(V))
    g = np.zeros(len(V))
    f[ref.src], g[ref.src] = ref.f, ref.g
    tri = mtri.Triangulation(V[:, 0], V[:, 1], F)
    fi, gi = mtri.LinearTriInterpolator(tri, f), mtri.LinearTriInterpolator(tri, g)
    period = np.ptp(ref.g[ref.inner])
    for start in ((0.12, 0.5), (0.85, 0.8), (0.2, 0.9), (0.75, 0.45)):
        p, gs = np.array(start, float), []
        for _ in range(400):  # descend grad f to the rim
            gx, gy = fi.gradient(p[0], p[1])
            step = -np.array([float(gx), float(gy)])
            if not np.isfinite(step).all() or float(fi(*p)) < 0.03:
                break
            p = p + 0.002 * step / np.linalg.norm(step)
            gs.append(float(gi(*p)))
        gs = np.asarray([x for x in gs if np.isfinite(x)])
        assert len(gs) > 20 and np.ptp(gs) / period < 0.02


def test_harmonic_disk_baseline(face):
    _, region = face
    uv = harmonic_disk(region.vertices, region.faces, region.loops["outer"])
    r = np.linalg.norm(uv[region.loops["outer"]] - 0.5, axis=1)
    np.testing.assert_allclose(r, 0.5, atol=1e-12)
    assert (signed_areas(uv, region.faces) > 0).mean() > 0.99


def test_sequence_maps_consistently_and_round_trips_through_the_codec(tmp_path, capsys):
    from facesynth.cli import main
    from facesynth.codec.geometry import Quantiser, build_layout, sample_vertices
    from facesynth.mesh.holes import punch_hole

    s = synthetic_face_sequence(25, 3)
    cheek = int(np.argmin(np.linalg.norm(s["frames"][0][:, :2] - [-3.0, -0.6], axis=1)))
    _, faces, kept = punch_hole(s["frames"][0], s["faces"], cheek, 0.9)  # a scan with a hole
    local = np.full(len(s["frames"][0]), -1)
    local[kept] = np.arange(len(kept))
    s = {"frames": s["frames"][:, kept], "faces": faces, "landmarks": local[s["landmarks"]]}
    np.savez(tmp_path / "seq.npz", vertices=s["frames"], faces=s["faces"])
    np.save(tmp_path / "lm.npy", s["landmarks"])
    out = tmp_path / "v.npy"
    capsys.readouterr()
    assert main(["codec", "scan", str(tmp_path / "seq.npz"), str(out), "--landmarks", str(tmp_path / "lm.npy"),
                 "--size", "64", "--radius", "3.0", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["holes_filled"] == [1, 1, 1] and report["flipped"] == [0, 0, 0]
    assert main(["codec", "encode", str(out), str(tmp_path / "v.fsgv"), "--qp", "12", "--gop", "3"]) == 0
    assert main(["codec", "decode", str(tmp_path / "v.fsgv"), str(tmp_path / "d.npy")]) == 0
    side = np.load(out.with_suffix(".scan.npz"))
    q = Quantiser(side["lo"], side["hi"])
    dec = q.dequantise(np.load(tmp_path / "d.npy"))
    errs = []
    for t in range(3):
        uv, faces, src = side[f"uv_{t}"], side[f"faces_{t}"], side[f"source_{t}"]
        assert (src < 0).sum() > 0  # the patch vertices are in the region
        truth = s["frames"][t][src[src >= 0]]
        rec = sample_vertices(build_layout(faces, uv, 64), dec[t])[src >= 0]
        errs.append(np.linalg.norm(rec - truth, axis=1) / q.diag)
    errs = np.concatenate(errs)
    assert np.median(errs) < 2e-3 and np.percentile(errs, 99) < 2e-2 and errs.max() < 3e-2  # 64x64 + QP 12
    # the same features land on the same pixels in every frame: the eye corners stay put; the
    # mouth landmarks slide along the hole's outline as the lips stretch (arc length changes)
    lm = s["landmarks"]
    for ix, tol in ((np.r_[EYE_R, EYE_L], 0.5), (MOUTH_INNER, 5.0)):  # measured 0.0 and 4.7 px
        pix = []
        for t in range(3):
            pos = {int(v): k for k, v in enumerate(side[f"source_{t}"])}
            pix.append(np.array([side[f"uv_{t}"][pos[int(v)]] for v in lm[ix]]) * 64)
        assert max(np.abs(p - pix[0]).max() for p in pix) < tol


def test_process_scan_errors_and_drift(face):
    f, _ = face
    with pytest.raises(FacesynthError, match="method"):
        process_scan(f["vertices"], f["faces"], f["landmarks"], 3.0, method="lscm")
    with pytest.raises(FacesynthError, match="landmarks"):
        process_scan(f["vertices"], f["faces"], f["landmarks"][:10], 3.0)
    fr = [process_scan(f["vertices"], f["faces"], f["landmarks"], 3.0)] * 2
    assert uv_drift(fr, 256)["max_px"] == 0.0


def test_cli_scan_bad_input(tmp_path, capsys):
    from facesynth.cli import main

    np.savez(tmp_path / "bad.npz", vertices=np.zeros((3, 3)))
    np.save(tmp_path / "lm.npy", np.arange(68))
    assert main(["codec", "scan", str(tmp_path / "bad.npz"), str(tmp_path / "o.npy"),
                 "--landmarks", str(tmp_path / "lm.npy")]) == 2
    assert "faces" in capsys.readouterr().err
    assert not (tmp_path / "o.npy").exists()


@pytest.mark.shared
def test_ict_expressions_segment_alike_and_map_bijectively(shared_mesh):
    from facesynth.codec.sources import load_ict_mesh

    m = load_ict_mesh(shared_mesh)
    names = json.loads((shared_mesh / "ict_face_9409_blendshape_names.json").read_text())
    mp = json.loads((shared_mesh / "ict_face_9409_ibug68_map.json").read_text())["map"]
    lm = np.array([mp[str(k)] for k in range(1, 69)])
    shapes = [names.index(n) for n in ("eyeBlink_L", "mouthSmile_R")]
    frames = [process_scan(m["vertices"], m["faces"], lm)]
    frames += [process_scan(m["vertices"] + m["blendshapes"][k], m["faces"], lm) for k in shapes]
    assert all(fr.flipped == 0 for fr in frames)
    kept = [set(segment_face(m["vertices"] + (0 if k is None else m["blendshapes"][k]), m["faces"], lm, 6.0,
                             remove_features=False).kept.tolist()) for k in (None, *shapes)]
    for other in kept[1:]:
        assert len(kept[0] ^ other) / len(kept[0]) <= 0.01
    drift = uv_drift(frames, 256, skip_rings=3)
    assert drift["mean_px"] < 5.0
    # a scan with two holes (cheek, brow) is filled, then parameterised bijectively
    from facesynth.mesh.holes import punch_hole

    V1, F1, kept = punch_hole(m["vertices"], m["faces"], 1200, 1.0)
    V2, F2, k2 = punch_hole(V1, F1, int(np.nonzero(kept == lm[19])[0][0]), 0.8)
    local = np.full(len(m["vertices"]), -1)
    local[kept[k2]] = np.arange(len(k2))
    fr = process_scan(V2, F2, local[lm])
    assert fr.filled == 2 and fr.flipped == 0 and (fr.source < 0).sum() > 20


@pytest.mark.shared
def test_ict_segmentation_is_stable_under_the_hardest_mouth_expressions(shared_mesh):
    """The issue's <= 1 % kept-set change at a fixed 6 cm radius, on the blendshapes that break
    the paper's eye + mouth sources (docs/codec.md: up to 2.7 % there)."""
    from facesynth.codec.sources import load_ict_mesh

    m = load_ict_mesh(shared_mesh)
    names = json.loads((shared_mesh / "ict_face_9409_blendshape_names.json").read_text())
    mp = json.loads((shared_mesh / "ict_face_9409_ibug68_map.json").read_text())["map"]
    lm = np.array([mp[str(k)] for k in range(1, 69)])

    def kept(V):
        return set(segment_face(V, m["faces"], lm, 6.0, remove_features=False).kept.tolist())

    base = kept(m["vertices"])
    for name in ("jawOpen", "mouthClose", "mouthLeft", "mouthPucker"):
        change = len(base ^ kept(m["vertices"] + m["blendshapes"][names.index(name)])) / len(base)
        assert change <= 0.01, (name, change)  # measured: jawOpen 0.83 %, mouthClose 0.69 %, the others < 0.55 %
