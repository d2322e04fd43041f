"""The contract of facesynth's ONNX files, shared by the exporter (:mod:`facesynth.onnx`,
torch) and the runtime (:mod:`facesynth.runtime`, torch-free): format strings, input and
output names, output layouts and the metadata keys every file carries.

A change here is a change of the file format: bump the ``/N`` of the format string.
"""

from __future__ import annotations

from facesynth.landmarks import DEFAULT_SCHEME

OPSET = 18

SYNTHESIS_FORMAT = "facesynth.synthesis.onnx/1"
ERI_FORMAT = "facesynth.eri.onnx/2"  # 2: frame_size [W, H] as in every other file (1: (H, W))
ERI_FORMAT_V1 = "facesynth.eri.onnx/1"  # still read: its frame_size is (H, W)
TALKING_HEAD_FORMAT = "facesynth.talking-head.onnx/2"  # 2: the feather in crop pixels, the frame warp on a grid
LANDMARK_SCHEME = DEFAULT_SCHEME.name
N_LANDMARKS = DEFAULT_SCHEME.n_points

SYNTHESIS_INPUT = "landmarks"
ERI_INPUT = "faps"
OUTPUT_NAMES = ("crop", "mask", "placement")
# a talking-head file's graph, checked before a file is accepted (facesynth.runtime.talking_head):
# each input and output, in order: name -> (element type, rank); the batch axis B is dynamic,
# P = the metadata's n_landmarks, (W, H) = its frame_size
TALKING_HEAD_SIGNATURE = {
    "inputs": {"driver": ("float32", 3), "driver_neutral": ("float32", 2)},  # (B, P, 2), (P, 2)
    "outputs": {"frame": ("uint8", 4), "avatar_landmarks": ("float32", 3)},  # (B, H, W, 3), (B, P, 2)
}
TALKING_HEAD_METADATA_KEYS = (
    "facesynth_version", "format", "landmark_scheme", "n_landmarks", "frame_size", "feather", "avatar_neutral",
    "background_jpeg", "output_layout", "opset",
)

TALKING_HEAD_INPUTS = tuple(TALKING_HEAD_SIGNATURE["inputs"])  # ("driver", "driver_neutral")
TALKING_HEAD_OUTPUTS = tuple(TALKING_HEAD_SIGNATURE["outputs"])  # ("frame", "avatar_landmarks")

SYNTHESIS_OUTPUT_LAYOUT = (
    "crop: float32 (B, C, H, W) in [0, 1], zeros outside the face; mask: float32 (B, 1, H, W) in {0, 1}; "
    "placement: float32 (B, 2, 3) affine map from crop pixels (x, y) to frame pixels"
)
TALKING_HEAD_LAYOUT = (
    "driver: float32 (B, P, 2) frame pixels; driver_neutral: float32 (P, 2) -> frame: uint8 (B, H, W, 3) RGB, the "
    "avatar's whole frame; avatar_landmarks: float32 (B, P, 2) its landmarks in that frame"
)
ERI_OUTPUT_LAYOUT = (
    "crop: float32 (B, 3, H, W) in [0, 1], zeros outside the face; mask: float32 (B, 1, H, W) in {0, 1}; "
    "placement: float32 (B, 2, 3) affine map from crop pixels (x, y) to the target's frame pixels"
)

SYNTHESIS_METADATA_KEYS = (
    "facesynth_version", "format", "regressor", "landmark_scheme", "n_landmarks", "reference_size",
    "channels", "data_fingerprint", "output_layout", "opset",
)
ERI_METADATA_KEYS = (
    "facesynth_version", "format", "kind", "driver", "raw_ratios", "n_faps", "fap_names", "landmark_scheme",
    "reference_size", "canvas_size", "frame_size", "data_fingerprint", "target_fingerprint", "feather",
    "output_layout", "opset",
)

# optional keys of a synthesis file that can be driven by another face (written by
# facesynth.onnx.avatar, read by facesynth.runtime.reenact): the avatar's neutral landmarks
# (68, 2) frame px, their clip row, the shape PCA {mean, components, limit}, the avatar's
# own frame (base64 JPEG) and its size [W, H], and (478-point avatars) the training frames as the
# studio's coverage meter reads them (facesynth.coverage.recording_entry; read by the live page)
AVATAR_METADATA_KEYS = ("avatar_neutral", "avatar_neutral_row", "avatar_neutral_rule", "shape_pca", "background_jpeg",
                        "frame_size", "coverage_recording")

# Every metadata field of every file kind: its order and unit, written once. Sizes of a frame
# (what a person calls "W x H") are [W, H]; sizes of the arrays a model renders into (the
# reference frame, the crop canvas) follow the arrays' (H, W) shape; points are (x, y) pixels.
METADATA_FIELDS = {
    "facesynth_version": "str: the package version that wrote the file",
    "format": "str: the file kind and its version (SYNTHESIS_FORMAT, ERI_FORMAT, TALKING_HEAD_FORMAT)",
    "opset": "int: the ONNX opset",
    "output_layout": "str: the outputs' shapes and units (the *_LAYOUT strings above)",
    "landmark_scheme": "str: the landmark scheme's name (facesynth.landmarks)",
    "n_landmarks": "int: P, points per face of the scheme",
    "frame_size": "[W, H] int pixels: the frame the outputs are placed in (the avatar's, the ERI target's)",
    "reference_size": "[H, W] int pixels: the face model's reference frame (an array shape)",
    "canvas_size": "[H, W] int pixels: the rendered crop (the crop and mask outputs' last two axes)",
    "channels": "int: 1 (grey) or 3 (RGB) channels of the crop",
    "feather": "float: the seam's width in pixels of the rendered crop (ERI: frame pixels, composite())",
    "regressor": "str: the SADM regressor's name",
    "data_fingerprint": "str: hex fingerprint of the training data (facesynth.provenance)",
    "target_fingerprint": "str: hex fingerprint of the ERI target's image and landmarks",
    "avatar_neutral": "(P, 2) float (x, y) pixels of frame_size: the avatar's neutral landmarks (its eyes the clip's typical ones)",
    "avatar_neutral_row": "int: the neutral's row in the training clip",
    "avatar_neutral_rule": "str: how the neutral was chosen (facesynth.neutral.select_neutral)",
    "shape_pca": "{mean (2P,), components (K, 2P), limit (K,)}: the avatar's shape PCA, (x, y) interleaved",
    "background_jpeg": "str: base64 JPEG of the avatar's neutral frame, frame_size [W, H]",
    "coverage_recording": "{features [F names], scale (F,), neutral (F,), keep_fps int or null, z (T, F)}: the training "
                          "frames kept at keep_fps frames/s (all when null), T <= 1000, as the coverage meter's F features "
                          "(facesynth.coverage.FEATURES: ratios of distances), z = (features - neutral) / scale, neutral "
                          "the features of avatar_neutral; 478-point avatars only",
    "frame_motion": "{coefficients (K - P, 2), ...}: the full-frame warp's learned motion (facesynth.onnx.headmotion)",
    "kind": "str: 'eri'",
    "driver": "str: the ERI model's SVR variant",
    "raw_ratios": "bool: ratios applied without edge confidence or brightening cap",
    "n_faps": "int: MPEG-4 FAPs per frame (the input's last axis)",
    "fap_names": "[str]: the FAPs' names, in input column order",
    "appearance_code_levels": "int: the int8 basis's weight code range (CODE_LEVELS below)",
    "appearance_basis": "str: 'int8' or 'float32', how the appearance basis is stored",
    "appearance_basis_bytes": "int: bytes of the stored appearance basis",
    "appearance_components": "int: appearance components kept at export",
    "appearance_components_full": "int: appearance components of the trained model",
    "compression": "str: how the components were chosen ('none', 'components', 'predicted_variance')",
    "predicted_variance": "float: the fraction of predicted variance the kept components hold",
    "quantization_psnr_vs_float_db": "float dB: the int8 basis's faces against float32's",
    "quantization_frames": "int: training frames that PSNR was measured on",
    "run": "str: the training run folder the file was exported from",
    "int32_index_gathers": "int: gathers whose indices the export pass made int32 (facesynth.onnx.passes)",
    "n_scanline_events": "int: the render warp's scanline events per face (facesynth.model.warp)",
    "eigeneri_components": "int: the ERI model's ratio-image PCA components",
    "support_vectors": "int: the ERI SVRs' support vectors",
    "distinct_support_vectors": "int: the distinct ones among them (shared in the graph)",
}

# what a file of each format is, for error messages that point to the right class
FORMAT_HINTS = {
    ERI_FORMAT: "an ERI model: use facesynth.runtime.EriRenderer",
    ERI_FORMAT_V1: "an ERI model: use facesynth.runtime.EriRenderer",
    SYNTHESIS_FORMAT: "a landmark-driven model: use facesynth.runtime.Renderer",
    TALKING_HEAD_FORMAT: "a talking head: use facesynth.runtime.TalkingHead",
}

# The int8 appearance basis (facesynth.ops.int8_matmul, one MatMulInteger u8 x s8): coefficient
# codes a in [-127, 127] travel as uint8 a + 128; weight codes q in [-CODE_LEVELS, CODE_LEVELS].
# x86 without VNNI adds pairs of u8 x s8 products in a saturating int16 (vpmaddubsw): exact only
# while 2 * 255 * |q| <= 32767. Files record their range as the metadata key "appearance_code_levels";
# int8 files without it were written with LEGACY_CODE_LEVELS and saturate on such CPUs.
COEF_LEVELS = 127
ZERO_POINT = 128  # the activation zero point: uint8 a + 128
U8_MAX, INT16_MAX = 255, 2**15 - 1
CODE_LEVELS = INT16_MAX // (2 * U8_MAX)  # 64: 2 * 255 * 64 = 32640
LEGACY_CODE_LEVELS = 127
CODE_LEVELS_KEY = "appearance_code_levels"


# The int8 parity contract: what torch and ONNX Runtime may disagree on, for a file with the int8
# basis (facesynth.onnx.int8check.tie_allowance computes it; the export checks and every parity test
# use it). Both compute the scaled coefficients x_k = b_k * COEF_LEVELS / limit_k with float sums in
# different orders (and in ONNX Runtime, in an order that depends on the CPU's kernels), so they agree
# on x only to float noise. Where x lies on a rounding tie (an integer + 1/2), one side may round up
# and the other down: that code differs by one step, which moves texel n by exactly |q_kn| s_n. So:
# * a code may differ by one step only, and only where the two values of x lie within
#   INT8_TIE_TOL (code units) of each other, i.e. both on the tie between them;
# * a crop (texture units, [0, 1]) may differ by FLOAT_PARITY_TOL plus, per frame, the largest sum
#   over texels of one step of each code that differs (0 when no code differs).
# Anything else is a wrong file.
FLOAT_PARITY_TOL = 1e-4
INT8_TIE_TOL = 0.05


def pair_sum_bound(code_levels: int) -> int:
    """Largest |u8 x s8 + u8 x s8| of the int8 appearance matmul with weight codes in
    [-code_levels, code_levels] and activations in [0, 255]; int16-safe when <= INT16_MAX."""
    return 2 * U8_MAX * int(code_levels)
