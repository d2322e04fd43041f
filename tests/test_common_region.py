"""psnr_frame_common's region (facesynth.eval.common_region): the masks against an
independent construction, where the dlib landmarks come from, and the figures in a run."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _faces import face_template
from matplotlib.path import Path as MplPath
from scipy.ndimage import distance_transform_edt
from scipy.spatial import ConvexHull

from facesynth.data import FaceSequence
from facesynth.errors import FacesynthError
from facesynth.eval.common_region import common_landmarks, region_masks
from facesynth.eval.regions_gap import combine, needed, scheme_gap, substitute
from facesynth.landmarks import FACE_REGIONS, MOUTH_CLOSED, face_region_masks, mouth_open


def _inside(poly: np.ndarray, shape) -> np.ndarray:
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]]
    return MplPath(poly).contains_points(np.stack([xs.ravel(), ys.ravel()], -1)).reshape(shape)


def test_region_masks_match_an_independent_construction():
    lm = face_template(width=120, cx=100, cy=110).astype(np.float64) + 0.37
    box = (10, 200, 5, 190)
    masks = region_masks(lm, box)
    shape = (box[1] - box[0], box[3] - box[2])
    local = lm - (box[2], box[0])
    hull = local[:27][ConvexHull(local[:27]).vertices]
    want = distance_transform_edt(_inside(hull, shape)) > 3  # inside the hull, more than 3 px from its outside
    whole = masks["whole"]
    assert (whole != want).sum() <= 0.02 * want.sum()  # only boundary pixels may differ (fill/erosion conventions)
    eyes = (_inside(local[36:42], shape) | _inside(local[42:48], shape)) & whole
    mouth = _inside(local[60:68], shape) & whole

    def perimeter(p):
        return float(np.linalg.norm(p - np.roll(p, 1, 0), axis=1).sum())

    # only pixels along the polygons' edges may differ (whether a centre on the edge is in)
    assert (masks["eyes"] != eyes).sum() <= perimeter(local[36:42]) + perimeter(local[42:48]) and eyes.sum() > 100
    assert (masks["mouth_interior"] != mouth).sum() <= perimeter(local[60:68]) and mouth.sum() > 100
    # the regions partition the common region
    parts = sum(masks[p].astype(int) for p in FACE_REGIONS)
    assert (parts[whole] == 1).all() and (parts[~whole] == 0).all()
    # lips: the outer-lip ring around the interior; brows: the band between each brow and its upper lid
    lips = _inside(local[48:60], shape) & whole & ~mouth & ~eyes
    assert (masks["lips"] != lips).sum() <= perimeter(local[48:60]) + perimeter(local[60:68]) and lips.sum() > 100
    right, left = np.r_[local[17:22], local[[39, 38, 37, 36]]], np.r_[local[22:27], local[[45, 44, 43, 42]]]
    band = (_inside(right, shape) | _inside(left, shape)) & whole & ~eyes & ~mouth & ~lips
    edges = perimeter(right) + perimeter(left) + perimeter(local[36:48]) + perimeter(local[48:60])
    assert (masks["brows"] != band).sum() <= edges and band.sum() > 50



def test_a_closed_mouth_has_no_interior():
    """The inner-lip polygon is the mouth interior only when the mouth is open (mouth_open above
    MOUTH_CLOSED, the neutral frame's rule); a closed mouth's polygon is the line where the lips
    meet, and goes to the lips. Either way the parts partition the image."""
    open_lm = face_template(width=120, cx=100, cy=110).astype(np.float64)
    upper, lower = [61, 62, 63], [67, 66, 65]
    mid = (open_lm[upper] + open_lm[lower]) / 2
    iod = float(np.linalg.norm(open_lm[36] - open_lm[45]))
    shape = (220, 200)
    for gap, has_interior in ((0.2, True), (0.031, True), (0.029, False), (0.0, False)):
        lm = open_lm.copy()
        lm[upper], lm[lower] = mid - [0, gap * iod / 2], mid + [0, gap * iod / 2]
        assert mouth_open(lm) == pytest.approx(gap, abs=1e-9)
        masks = face_region_masks(lm, shape)
        polygon = _inside(lm[60:68], shape)
        assert masks["mouth_interior"].any() == has_interior
        assert sum(masks[p].astype(int) for p in FACE_REGIONS).max() == 1
        assert sum(masks[p].astype(int) for p in FACE_REGIONS).min() == 1
        if has_interior:
            assert (masks["mouth_interior"] != polygon).sum() <= 2 * np.linalg.norm(lm[60:68] - np.roll(lm[60:68], 1, 0), axis=1).sum()
        else:  # the sliver between the lips is lips
            assert not (polygon & ~masks["lips"] & ~masks["eyes"]).any()

def test_common_landmarks_sources(tmp_path):
    lm68 = face_template()[None].repeat(6, 0) + np.arange(6, dtype=np.float32)[:, None, None]
    own = FaceSequence(lm68[1:], np.arange(1, 6), name="own")
    np.testing.assert_array_equal(common_landmarks(own), lm68[1:])  # an ibug68 sequence: its own points
    # a 478-point sequence: the 68 points beside the video that its meta.json records, by video frame
    clip = tmp_path / "clip"
    clip.mkdir()
    np.save(clip / "landmarks.npy", lm68)
    lm478 = np.zeros((3, 478, 2), np.float32)
    meta = {"video": {"path": str(clip / "video.mp4")}}
    dense = FaceSequence(lm478, np.array([0, 2, 5]), name="dense", meta=meta, scheme="mediapipe478")
    np.testing.assert_array_equal(common_landmarks(dense), lm68[[0, 2, 5]])
    np.testing.assert_array_equal(common_landmarks(dense, str(clip)), lm68[[0, 2, 5]])  # eval.common_landmarks
    with pytest.raises(FacesynthError, match=r"dense: psnr_frame_common needs the clip's dlib 68 landmarks .*eval\.common_landmarks"):
        common_landmarks(FaceSequence(lm478, np.arange(3), name="dense", scheme="mediapipe478"))
    np.save(tmp_path / "short.npy", lm68[:4])
    with pytest.raises(FacesynthError, match=r"short\.npy: 4 frames of common landmarks, but dense uses video frame 5"):
        common_landmarks(dense, str(tmp_path / "short.npy"))
    np.save(tmp_path / "dense.npy", np.zeros((6, 478, 2), np.float32))
    with pytest.raises(FacesynthError, match=r"must be dlib's 68 points \(T, 68, 2\), got \(6, 478, 2\)"):
        common_landmarks(dense, str(tmp_path / "dense.npy"))


def test_psnr_frame_common_in_an_evaluation(shared_mesh):
    """Both schemes' models on the same synthetic frames: the common figures exist for every
    row and noise level; the mean texture and rewarp rows order as expected; on an ibug68
    model the common region lies inside the face region, so both measure nearly alike."""
    from _dense import dense_sequence

    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.sadm.fit import fit_sadm

    seq68 = make_synthetic_sequence(n_frames=40, size=160, seed=5)
    cfg = EvalConfig(noise=[0.0, 1.0], max_test_frames=8, train_level=False)
    tr, te = np.arange(30), np.arange(30, 40)
    out = {}
    for seq in (seq68, dense_sequence(seq68, shared_mesh / "mediapipe_canonical_468_arrays.npz")):
        model, tex = FaceModel.fit_with_textures(seq, FaceModelConfig(reference_width=64), rows=tr, progress=False)
        sadm = fit_sadm(model, seq, tr, tex, "linear")
        metrics, _ = evaluate_sadm(sadm, seq, tr, te, cfg, 0, train_textures=tex, common=seq68.landmarks)
        json.dumps(metrics)
        regions = metrics["psnr_frame_common_regions"]
        # the synthetic faces never open their mouths: no mouth interior in any frame, so none in the tables
        assert (mouth_open(seq68.landmarks[te]) <= MOUTH_CLOSED).all()
        shown = [p for p in FACE_REGIONS if p != "mouth_interior"]
        assert set(regions) == {"whole", *shown}
        sharp = metrics["sharpness_frame_common"]  # the rendered face's detail against the real frame's
        assert set(sharp) == {"whole", *shown} and set(sharp["whole"]) == {"sadm", "mean_texture", "oracle", "rewarp"}
        assert 0 < sharp["whole"]["mean_texture"] < sharp["whole"]["rewarp"] < 1.5
        assert metrics["psnr_frame_common"] == regions["whole"]
        for table in regions.values():
            assert set(table) == {"sadm", "mean_texture", "oracle", "rewarp"} and all(set(v) == {"0", "1"} for v in table.values())
        c = metrics["psnr_frame_common"]
        assert c["rewarp"]["0"] > c["mean_texture"]["0"]
        # the parts partition the region: their shares sum to 1 and their figures recombine into the whole's
        shares = metrics["psnr_frame_common_shares"]
        assert set(shares) == set(regions) and shares["whole"] == 1.0
        assert sum(shares[p] for p in shown) == pytest.approx(1.0, abs=1e-12)
        assert all(0 < shares[p] < 1 for p in shown)
        for row in c:
            for k in ("0", "1"):
                assert combine(shares, {p: regions[p][row][k] for p in shown}) == pytest.approx(c[row][k], abs=1e-9)
        out[seq.scheme] = metrics
    ib = out["ibug68"]
    assert abs(ib["psnr_frame_common"]["rewarp"]["0"] - ib["psnr_frame"]["rewarp"]["0"]) < 2.0


PARTS = ("eyes", "mouth_interior", "rest")  # a run measured before lips and brows were split off


def _metrics(parts: dict, shares: dict, oracle: dict) -> dict:
    rows = {p: {"sadm": {"0": parts[p]}, "oracle": {"0": oracle[p]}} for p in PARTS}
    whole = {"sadm": {"0": combine(shares, parts)}, "oracle": {"0": combine(shares, oracle)}}
    return {"psnr_frame_common_regions": {"whole": whole, **rows}, "psnr_frame_common_shares": {"whole": 1.0, **shares}}


def test_regions_gap_arithmetic_against_closed_forms():
    shares = {"eyes": 0.03, "mouth_interior": 0.02, "rest": 0.95}
    assert combine(shares, dict.fromkeys(PARTS, 27.0)) == pytest.approx(27.0)
    # two equal halves at 20 and 30 dB: mse = (10^-2 + 10^-3) / 2
    assert combine({"eyes": 0.5, "mouth_interior": 0.0, "rest": 0.5}, {"eyes": 20.0, "mouth_interior": 99.0, "rest": 30.0}) \
        == pytest.approx(-10 * np.log10(0.0055))
    m = _metrics({"eyes": 18.0, "mouth_interior": 17.0, "rest": 28.0}, shares, {"eyes": 25.0, "mouth_interior": 24.0, "rest": 32.0})
    at = {"eyes": "oracle", "mouth_interior": "oracle"}
    assert substitute(m, {}) == pytest.approx(m["psnr_frame_common_regions"]["whole"]["sadm"]["0"])
    assert substitute(m, {p: "oracle" for p in PARTS}) == pytest.approx(m["psnr_frame_common_regions"]["whole"]["oracle"]["0"])
    for rows in (None, at):
        need = needed(m, "rest", 28.0, rows)  # put back, it gives the target exactly
        parts = {p: m["psnr_frame_common_regions"][p][(rows or {}).get(p, "sadm")]["0"] for p in PARTS}
        assert combine(shares, {**parts, "rest": need}) == pytest.approx(28.0)
    assert needed(m, "rest", 40.0) == np.inf  # the eyes alone exceed a 40 dB budget
    base = _metrics({"eyes": 17.0, "mouth_interior": 17.5, "rest": 27.9}, shares, dict.fromkeys(PARTS, 30.0))
    gap = scheme_gap(m, base, 1.0)
    assert gap["target"] == pytest.approx(base["psnr_frame_common_regions"]["whole"]["sadm"]["0"] + 1.0)
    assert gap["difference"] == pytest.approx(gap["whole_dense"] - gap["whole_base"])
    assert gap["rest_needed_eyes_mouth_at_oracle"] < gap["rest_needed"]
    with pytest.raises(FacesynthError, match="run.json: no psnr_frame_common_regions"):
        scheme_gap({}, base, where=("run.json", "b"))
