"""A clip's neutral with its eyes where the clip's usually are (facesynth.neutral.typical_eyes):
the median in each eye's corner frame, checked against complex-number arithmetic; invariant to
a similarity; and, driving a face by its own clip from two neutral frames that look different
ways, the retargeted irises land where the frame's are only when both neutrals take it."""

from __future__ import annotations

import numpy as np
import pytest
from _dense import dense_sequence

from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.neutral import typical_eyes
from facesynth.retarget import Retargeter

# (corner a, corner b, the eye's points) per eye, from the schemes' regions
EYES = {"ibug68": [(36, 39, range(36, 42)), (42, 45, range(42, 48))],
        "ibug68+iris": [(36, 39, [*range(36, 42), *range(68, 73)]), (42, 45, [*range(42, 48), *range(73, 78)])]}


def _complex(lm):
    return lm[..., 0] + 1j * lm[..., 1]


def _reference(neutral, frames, scheme):
    """The same definition in complex numbers: z = (p - a) / (b - a) per frame, the median of
    its real and imaginary parts, put back as a + z (b - a) on the neutral's corners."""
    out = neutral.copy()
    n, f = _complex(neutral), _complex(frames)
    for a, b, pts in EYES[scheme]:
        pts = list(pts)
        z = (f[:, pts] - f[:, [a]]) / (f[:, [b]] - f[:, [a]])
        zm = np.median(z.real, 0) + 1j * np.median(z.imag, 0)
        p = n[a] + zm * (n[b] - n[a])
        out[pts] = np.stack([p.real, p.imag], -1)
    return out


@pytest.mark.parametrize("scheme", ["ibug68", "ibug68+iris"])
def test_typical_eyes_is_the_median_in_each_eyes_frame(scheme, rng):
    p = get_scheme(scheme).n_points
    base = rng.uniform(20, 140, (p, 2))
    frames = np.repeat(base[None], 25, 0)
    eyes = sorted({i for _, _, pts in EYES[scheme] for i in pts} - {36, 39, 42, 45})
    frames[:, eyes] += rng.normal(0, 2.0, (25, len(eyes), 2))  # the eyes move, frame by frame
    th = rng.uniform(-0.3, 0.3, 25)  # and every frame is a different similarity of the face
    k = rng.uniform(0.8, 1.3, 25)
    rot = k[:, None, None] * np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], 1)
    frames = np.einsum("nij,npj->npi", rot, frames) + rng.uniform(-20, 20, (25, 1, 2))
    frames[4] = np.nan  # a row without a face is left out
    neutral = frames[7]
    got = typical_eyes(neutral, frames)
    np.testing.assert_allclose(got, _reference(neutral, np.delete(frames, 4, 0), scheme), atol=1e-9)
    others = np.setdiff1d(np.arange(p), eyes)
    np.testing.assert_array_equal(got[others], neutral[others])  # the corners and the rest stay
    # a similarity of everything moves the result with it
    s = 1.7 * np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
    np.testing.assert_allclose(typical_eyes(neutral @ s.T + 5, frames @ s.T + 5), got @ s.T + 5, atol=1e-9)
    # frames that are all the neutral leave it as it is
    np.testing.assert_allclose(typical_eyes(neutral, np.repeat(neutral[None], 3, 0)), neutral, atol=1e-9)


def test_typical_eyes_refuses_mismatched_shapes():
    with pytest.raises(FacesynthError, match=r"typical_eyes: a \(P, 2\) neutral and \(N, P, 2\) landmarks"):
        typical_eyes(np.zeros((68, 2)), np.zeros((3, 478, 2)))
    with pytest.raises(FacesynthError, match="typical_eyes"):
        typical_eyes(np.zeros((50, 2)), np.zeros((3, 50, 2)))


def test_self_driving_keeps_the_gaze_only_with_typical_eyes_on_both_sides(shared_mesh, rng):
    """A 478-point clip whose irises look left and right (a share of each eye's width along
    it), driven by itself from two neutral frames chosen to look opposite ways: relative motion
    keeps their difference (0.3 eye widths) in every frame; with both neutrals' eyes typical,
    the retargeted irises are where the frame's are."""
    sch = get_scheme("mediapipe478")
    seq = dense_sequence(make_synthetic_sequence(n_frames=40, size=160, seed=3), shared_mesh / "mediapipe_canonical_468_arrays.npz")
    lm = seq.landmarks.astype(np.float64)
    gaze = rng.uniform(-0.1, 0.1, len(lm))
    gaze[[5, 30]] = 0.15, -0.15  # the two neutral frames look opposite ways
    corners = [int(i) for i in sch.regions["eye_corners"]]
    for (a, b), iris in zip([corners[:2], corners[2:]], ("right_iris", "left_iris"), strict=True):
        pts = list(sch.regions[iris])
        lm[:, pts] += gaze[:, None, None] * (lm[:, [b]] - lm[:, [a]])

    def iris_along(x):  # the iris centres' place along their eye, in eye widths
        c = [int(i) for i in sch.regions["iris_centres"]]
        e = [(x[..., corners[1], :] - x[..., corners[0], :]), (x[..., corners[3], :] - x[..., corners[2], :])]
        v = [x[..., c[0], :] - x[..., corners[0], :], x[..., c[1], :] - x[..., corners[2], :]]
        return np.stack([(vi * ei).sum(-1) / (ei ** 2).sum(-1) for vi, ei in zip(v, e, strict=True)], -1)

    rows = [0, 12, 21, 35]
    today = Retargeter(lm[5], lm[30], scheme="mediapipe478")(lm[rows])
    off = np.abs(iris_along(today) - iris_along(lm[rows]))
    assert off.min() > 0.25  # the neutrals' 0.3 eye widths apart, in every frame
    both = Retargeter(typical_eyes(lm[5], lm), typical_eyes(lm[30], lm), scheme="mediapipe478")(lm[rows])
    assert np.abs(iris_along(both) - iris_along(lm[rows])).max() < 0.02
