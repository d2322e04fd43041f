import json

import numpy as np
import pytest

from facesynth.data import (
    FaceSequence,
    load_landmarks,
    load_sequence,
    read_pts,
    save_landmarks,
    temporal_split,
    write_pts,
)
from facesynth.errors import FacesynthError


def test_pts_round_trip_is_one_based_on_disk(tmp_path, rng):
    lm = rng.uniform(0, 200, (68, 2)).astype(np.float32)
    write_pts(tmp_path / "a.pts", lm)
    text = (tmp_path / "a.pts").read_text()
    first = [float(t) for t in text.splitlines()[3].split()]
    assert first == pytest.approx((lm[0] + 1).tolist(), abs=1e-3)
    np.testing.assert_allclose(read_pts(tmp_path / "a.pts"), lm, atol=1e-3)


def test_pts_wrong_count_names_file(tmp_path):
    write_pts(tmp_path / "b.pts", np.zeros((5, 2)))
    with pytest.raises(FacesynthError, match=r"b\.pts.*5 landmarks, expected 68"):
        read_pts(tmp_path / "b.pts")


def test_npy_nan_rows_dropped_and_counted(tmp_path, rng):
    lm = rng.uniform(0, 100, (10, 68, 2)).astype(np.float32)
    lm[[2, 7]] = np.nan
    np.save(tmp_path / "lm.npy", lm)
    seq = load_sequence(tmp_path / "lm.npy")
    assert len(seq) == 8 and seq.meta["dropped_frames"] == 2
    assert list(seq.frame_index) == [0, 1, 3, 4, 5, 6, 8, 9]


def test_wrong_shape_and_partial_nan_are_errors(tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((4, 67, 2), np.float32))
    with pytest.raises(FacesynthError, match=r"bad\.npy.*\(N, 68, 2\).*\(4, 67, 2\)"):
        load_sequence(tmp_path / "bad.npy")
    lm = np.zeros((3, 68, 2), np.float32)
    lm[1, 5, 0] = np.nan
    np.save(tmp_path / "part.npy", lm)
    with pytest.raises(FacesynthError, match="frame 1 contain NaN"):
        load_sequence(tmp_path / "part.npy")


def test_unknown_extension_and_missing_file(tmp_path):
    (tmp_path / "x.foo").write_text("")
    with pytest.raises(FacesynthError, match="unknown format '.foo'"):
        load_sequence(tmp_path / "x.foo")
    with pytest.raises(FacesynthError, match="no such file"):
        load_sequence(tmp_path / "nope.npy")


def test_writers_by_extension_round_trip(tmp_path, rng):
    lm = rng.uniform(0, 100, (3, 68, 2)).astype(np.float32)
    for name in ("a.npy", "a.npz", "ptsdir"):
        save_landmarks(tmp_path / name, lm)
    np.testing.assert_array_equal(load_landmarks(tmp_path / "a.npy"), lm)
    np.testing.assert_array_equal(load_sequence(tmp_path / "a.npz").landmarks, lm)
    np.testing.assert_allclose(np.stack([read_pts(p) for p in sorted((tmp_path / "ptsdir").glob("*.pts"))]), lm, atol=1e-3)


def test_image_folder_with_pts(tmp_path, rng):
    import cv2

    for i in range(3):
        img = np.full((40, 50, 3), 10 * i, np.uint8)
        img[0, 0] = (255, 0, 0)  # red in RGB
        cv2.imwrite(str(tmp_path / f"f{i}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        write_pts(tmp_path / f"f{i}.pts", rng.uniform(0, 40, (68, 2)))
    seq = load_sequence(tmp_path)
    assert len(seq) == 3 and seq.image_size == (40, 50)
    frame = seq.frame(2)
    assert frame.dtype == np.uint8 and tuple(frame[0, 0]) == (255, 0, 0) and frame[5, 5, 0] == 20


def test_temporal_split():
    tr, te = temporal_split(100, 0.75, gap=5)
    assert tr[-1] == 74 and te[0] == 80 and te[-1] == 99
    with pytest.raises(FacesynthError):
        temporal_split(3, 0.75, gap=5)


def test_sequence_reads_frames_in_any_order():
    from facesynth.data.frames import ArrayFrames

    frames = np.arange(5, dtype=np.uint8)[:, None, None, None] * np.ones((5, 4, 4, 3), np.uint8)
    seq = FaceSequence.from_arrays(np.zeros((5, 68, 2), np.float32), ArrayFrames(frames))
    assert [f[0, 0, 0] for f in seq.iter_frames([3, 1, 4])] == [3, 1, 4]


@pytest.mark.shared
def test_real_clip_ingest_layout(shared_clip_dir):
    clip = shared_clip_dir("lp_d0")
    seq = load_sequence(clip)
    meta = json.loads((clip / "meta.json").read_text())
    assert len(seq) == meta["video"]["frames"]
    assert seq.image_size == (meta["video"]["height"], meta["video"]["width"])
    later, earlier = seq.frame(40), seq.frame(3)  # backwards read reopens the video
    again = seq.frame(40)
    np.testing.assert_array_equal(later, again)
    assert earlier.shape == later.shape
