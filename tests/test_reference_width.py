"""model.reference_width=auto: the reference frame's width from the training faces' width in the video."""

from __future__ import annotations

import numpy as np
import pytest

from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.errors import FacesynthError
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.model.reference import AUTO_WIDTH, ReferenceFrame, reference_width


def _faces(width: float, n: int = 5) -> np.ndarray:
    """(n, 3, 2) landmark sets whose bounding boxes are ``width`` px wide (one set 10 px wider)."""
    lm = np.array([[0.0, 0.0], [width, 10.0], [width / 2, width]])[None].repeat(n, 0) + 40.0
    lm[0, 1, 0] += 10.0
    return lm


def test_auto_width_is_the_median_face_width_rounded_up_and_bounded():
    assert reference_width(200, _faces(999)) == 200 and reference_width(np.int64(96), _faces(1)) == 96
    assert reference_width("auto", _faces(200)) == 208  # median 200 -> next multiple of 16
    assert reference_width("auto", _faces(224)) == 224
    assert reference_width("auto", _faces(90)) == AUTO_WIDTH[0]
    assert reference_width("auto", _faces(700)) == AUTO_WIDTH[1]
    with pytest.raises(FacesynthError, match="model.reference_width"):
        reference_width("big", _faces(200))


def test_fit_with_auto_records_the_width_it_used():
    seq = make_synthetic_sequence(12, 256, seed=0)
    model = FaceModel.fit(seq, FaceModelConfig(reference_width="auto"), progress=False)
    want = reference_width("auto", seq.landmarks)
    assert model.config.reference_width == want and isinstance(model.config.reference_width, int)
    assert AUTO_WIDTH[0] <= want <= AUTO_WIDTH[1]
    same = ReferenceFrame.from_mean_shape(model.reference.points, want, model.config.margin)
    assert same.size == model.reference.size  # the reference is the mean at that width
