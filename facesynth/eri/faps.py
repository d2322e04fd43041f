"""MPEG-4 FAPs: the implementation lives in the ground module :mod:`facesynth.faps` (numpy
only, shared with the runtime's retargeting, :mod:`facesynth.retarget`); re-exported here."""

from facesynth.faps import (  # noqa: F401
    _FP_IDS,
    _FP_MATRIX,
    ANCHOR_POINTS,
    FAP_NAMES,
    FAP_TABLE,
    FAPU_NAMES,
    FEATURE_POINTS,
    N_FAPS,
    RIGID_POINTS,
    _fp,
    _interpolation,
    align_to_neutral,
    compute_faps,
    face_axes,
    fap_displacements,
    faps_to_landmarks,
    fapu,
    head_pose,
)
