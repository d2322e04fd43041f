"""The live reach readout's Python reference (facesynth.coverage: recording_entry, read_recording,
driver_reach): the avatar's recording entry against the training frames' features computed
apart (kept at the page's 15 frames a second, the avatar's neutral), a driver's reach against a
brute-force reference, its invariance to where the face is, and each malformed entry refused
with a one-line error naming the field. Real MediaPipe points of a shared clip (skips without
../shared or MediaPipe); the page's twin (coverage.js) is tested in tests/test_web_page.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from facesynth import coverage
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.neutral import select_neutral


@pytest.fixture(scope="module")
def clip(shared_clip_dir, tmp_path_factory):
    """lp_d6's first 150 frames through ``facesynth ingest --landmarker mediapipe`` (30 frames/s)."""
    pytest.importorskip("mediapipe")
    from facesynth.data.ingest import ingest_video

    seq = ingest_video(shared_clip_dir("lp_d6") / "video.mp4", tmp_path_factory.mktemp("mp"), landmarker="mediapipe",
                       max_frames=150)
    assert seq.fps == 30 and np.array_equal(seq.frame_index, np.arange(len(seq)))  # every frame has a face
    lm = seq.landmarks.astype(np.float64)
    return lm, lm[select_neutral(lm)[0]]


def test_recording_entry_against_the_frames_features(clip):
    lm, neutral = clip
    entry = coverage.recording_entry(lm, neutral, np.arange(len(lm)) / 30.0)
    # at 30 frames/s the page keeps every other frame (1/15 s apart)
    want = (coverage.features(lm[::2]) - coverage.features(neutral[None])[0]) / np.asarray(coverage.SCALE)
    z = np.asarray(entry["z"])
    assert z.shape == (75, 8) and np.abs(z - want).max() <= 0.5 * 10.0 ** -coverage.DECIMALS + 1e-12
    assert entry["features"] == list(coverage.FEATURES) and entry["scale"] == list(coverage.SCALE) and entry["keep_fps"] == 15
    np.testing.assert_allclose(entry["neutral"], coverage.features(neutral[None])[0], atol=1e-6)
    assert coverage.read_recording(entry)[0].shape == (75, 8)
    # times unknown: every frame; a frame without finite features is dropped
    broken = lm.copy()
    broken[7] = np.nan
    all_frames = coverage.recording_entry(broken, neutral)
    assert all_frames["keep_fps"] is None and len(all_frames["z"]) == len(lm) - 1
    np.testing.assert_allclose(all_frames["z"][7], np.round(want[4], coverage.DECIMALS))  # frame 8 follows frame 6
    # a cap: at most MAX_RECORDED rows, evenly spaced, the first and last kept
    capped = coverage.recording_entry(np.concatenate([lm] * 8), neutral)
    assert len(capped["z"]) == coverage.MAX_RECORDED == 1000
    np.testing.assert_allclose(capped["z"][0], all_frames["z"][0])
    np.testing.assert_allclose(capped["z"][-1], all_frames["z"][-1])
    # no usable neutral or no frame: no entry
    assert coverage.recording_entry(lm, np.zeros_like(neutral)) is None
    assert coverage.recording_entry(lm[:0], neutral) is None


def _brute_reach(rows: list[list[float]], scale: list[float], driver, neutral) -> float:
    """One driver frame's reach, written out: its z, the sorted distances to every recorded row,
    the mean of the NEAREST smallest, 1 - that / DRIVE_REACH, clipped to [0, 1]."""
    f, n = coverage.features(driver[None])[0], coverage.features(neutral[None])[0]
    z = [(float(f[k]) - float(n[k])) / scale[k] for k in range(len(scale))]
    dists = sorted(math.sqrt(sum((a - b) ** 2 for a, b in zip(z, row, strict=True))) for row in rows)
    d = sum(dists[:coverage.NEAREST]) / len(dists[:coverage.NEAREST])
    return min(1.0, max(0.0, 1.0 - d / coverage.DRIVE_REACH))


def test_driver_reach_against_brute_force(clip):
    lm, neutral = clip
    entry = coverage.recording_entry(lm, neutral, np.arange(len(lm)) / 30.0)  # the even frames
    driver = lm[1::2]  # the odd ones, from their own neutral
    driver_neutral = driver[select_neutral(driver)[0]]
    got = coverage.driver_reach(entry, driver, driver_neutral)
    want = [_brute_reach(entry["z"], entry["scale"], d, driver_neutral) for d in driver]
    assert got.shape == (75,) and np.abs(got - want).max() < 1e-12
    assert ((0 < got) & (got < 1)).sum() > 30  # most inside the clip's range
    assert coverage.driver_reach(entry, driver[3], driver_neutral) == got[3]
    # a far expression (the mouth wide open: the lower lip dropped by an eye-corner distance) is not reached
    wide = driver[0].copy()
    table = get_scheme("mediapipe478").ibug68_matrix()  # the lower lip: iBUG-68 points 55-59 and 64-67
    lower = np.flatnonzero(table[[*range(55, 60), *range(64, 68)]].any(0))
    wide[lower, 1] += np.linalg.norm(wide[33] - wide[263])
    assert coverage.driver_reach(entry, wide, driver_neutral) == 0.0
    # a similarity of driver and neutral together (the face elsewhere, larger, turned in the image) changes nothing
    c, s = math.cos(0.3), math.sin(0.3)
    move = lambda p: 1.7 * p @ np.array([[c, -s], [s, c]]).T + [40.0, -25.0]  # noqa: E731
    np.testing.assert_allclose(coverage.driver_reach(entry, move(driver), move(driver_neutral)), got, atol=1e-9)
    # the driver's own neutral reaches what the avatar's neutral does
    at_neutral = coverage.reach(np.asarray(entry["z"]), np.zeros(8), coverage.DRIVE_REACH)[0]
    assert coverage.driver_reach(entry, driver_neutral, driver_neutral) == at_neutral
    # a frame without finite features: NaN, not a reach
    assert np.isnan(coverage.driver_reach(entry, np.full((478, 2), np.nan), driver_neutral))


def test_malformed_entry_is_refused_naming_the_field(clip):
    lm, neutral = clip
    good = coverage.recording_entry(lm[:40], neutral)
    cases = {
        "expected an object": [1, 2],
        "are not the meter's": {**good, "features": good["features"][::-1]},
        "scale has shape 7": {**good, "scale": good["scale"][:7]},
        "scale has values that are not positive": {**good, "scale": [0.0] * 8},
        "neutral is not an array of numbers": {**good, "neutral": ["0"] * 8},
        "z has values that are not finite": {**good, "z": [*good["z"][:3], [float("nan")] * 8]},
        "z is not an array of numbers": {**good, "z": [[0.0] * 8, [0.0] * 7]},
        "z has shape 0": {**good, "z": []},
        "z has shape 3 x 9": {**good, "z": [[0.0] * 9] * 3},
    }
    for what, entry in cases.items():
        with pytest.raises(FacesynthError) as e:
            coverage.driver_reach(entry, lm[0], lm[1])
        msg = str(e.value)
        assert msg.startswith("coverage_recording: ") and what in msg and "\n" not in msg, msg
    with pytest.raises(FacesynthError, match="478-point frames"):
        coverage.driver_reach(good, lm[0, :68], lm[1])
