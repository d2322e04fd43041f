"""Data layer: sequences of frames + landmarks (iBUG 68 or MediaPipe 478 points),
readers/writers, splits, the synthetic default subject, and video ingest (dlib or
MediaPipe, optional extras)."""

from facesynth.data.pts import read_pts, write_pts
from facesynth.data.readers import load_landmarks, load_sequence, register_reader, register_writer, save_landmarks
from facesynth.data.sequence import FaceSequence, validate_landmarks
from facesynth.data.shared import shared_clip, shared_data_dir, shared_mesh_dir
from facesynth.data.splits import temporal_split
from facesynth.data.synthetic import make_synthetic_sequence
from facesynth.landmarks import N_LANDMARKS

__all__ = [
    "N_LANDMARKS", "FaceSequence", "load_landmarks", "load_sequence", "read_pts", "register_reader",
    "register_writer", "save_landmarks", "shared_clip", "shared_data_dir", "shared_mesh_dir", "make_synthetic_sequence",
    "temporal_split", "validate_landmarks", "write_pts",
]
