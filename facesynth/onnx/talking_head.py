"""The whole talking head as one ONNX graph (torch side; the runtime side is
:class:`facesynth.runtime.talking_head.TalkingHead`, torch-free):

    driver (B, P, 2) frame px, driver_neutral (P, 2) -> frame (B, H, W, 3) uint8,
                                                          avatar_landmarks (B, P, 2)

In between, the steps of the numpy reference pipeline (:class:`facesynth.runtime.Reenactor`
with ``full_frame``, relative motion), each as tensor ops (:mod:`facesynth.onnx.head_parts`):
the retargeting and shape clamp, the synthesis (:class:`SynthesisGraph`), the full-frame
warp of the avatar's neutral frame (its control points and Delaunay triangles, taken from
:class:`facesynth.runtime.fullframe.FrameWarp`) and the feathered, colour-matched seam.
The feather is fixed at export (``feather`` metadata, pixels of the rendered crop; by
default :func:`facesynth.compositing.seam_width` of the face's mask rendered at the
avatar's neutral), where ``blend_face`` measures it per frame.

Standard ONNX operators only (opset 18: Gather, GatherElements, ScatterElements, CumSum,
Pad, Slice, Range, MatMul, MatMulInteger, ...), none outside ONNX Runtime Web's.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from facesynth import __version__
from facesynth.compositing import seam_width
from facesynth.contract import OPSET, TALKING_HEAD_FORMAT, TALKING_HEAD_INPUTS, TALKING_HEAD_LAYOUT, TALKING_HEAD_OUTPUTS
from facesynth.errors import FacesynthError
from facesynth.landmarks import get_scheme
from facesynth.onnx.common import save_graph
from facesynth.onnx.head_parts import FrameWarpGraph, SeamGraph
from facesynth.onnx.retarget_graph import RetargetGraph
from facesynth.onnx.synthesis import SynthesisGraph, torch_reference
from facesynth.retarget import RETARGET_SCHEMES
from facesynth.runtime.reenact import Avatar

INPUTS, OUTPUTS = TALKING_HEAD_INPUTS, TALKING_HEAD_OUTPUTS


class TalkingHeadGraph(nn.Module):
    """Driver landmarks and the driver's neutral -> the composited avatar frame.

    syn : Synthesizer (ibug68 or mediapipe478: P = 68 or 478); avatar : :class:`facesynth.runtime.reenact.Avatar`
    (its neutral, shape PCA and neutral frame, from the model's metadata); feather : seam
    width in pixels (default: :func:`default_feather`).

    Forward: driver (B, P, 2), neutral (P, 2) float32 -> frame (B, H, W, 3) uint8,
    avatar landmarks (B, P, 2) float32.
    """

    def __init__(self, syn, avatar: Avatar, feather: float | None = None):
        super().__init__()
        scheme = str(getattr(syn, "scheme", "ibug68"))
        if scheme not in RETARGET_SCHEMES:
            raise FacesynthError(f"talking-head graph: takes {' or '.join(RETARGET_SCHEMES)} models, not {scheme}")
        frame = avatar.background
        if avatar.neutral is None or frame is None:
            raise FacesynthError(f"{avatar.where}: the talking-head graph needs the avatar's neutral and frame in the "
                                 "metadata (re-export the model)")
        self.synthesis = SynthesisGraph(syn.eval()).eval()
        self.retarget = RetargetGraph(avatar.neutral, avatar.shape_space, get_scheme(scheme))
        self.frame_warp = FrameWarpGraph(avatar.frame_warp())
        self.feather = float(default_feather(self.synthesis, avatar.neutral) if feather is None else feather)
        self.seam = SeamGraph(self.feather, (frame.shape[1], frame.shape[0]), tuple(syn.warp.canvas))

    def forward(self, driver: torch.Tensor, neutral: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        face = self.retarget(driver, neutral)
        crop, mask, placement = self.synthesis(face)
        out = self.seam(crop, mask, placement, self.frame_warp.read(face), face)  # uint8 (B, 3, H, W)
        return out.permute(0, 2, 3, 1), face


def default_feather(synthesis: SynthesisGraph, neutral: np.ndarray) -> float:
    """:func:`seam_width` (crop pixels) of the face's mask rendered at ``neutral`` (P, 2)."""
    with torch.no_grad():
        _, mask, _ = synthesis(torch.from_numpy(np.asarray(neutral, np.float32)[None]))
    return float(seam_width(mask[0, 0].numpy()))


def export_talking_head(syn, metadata: dict, path: str | os.PathLike, feather: float | None = None,
                        opset: int = OPSET) -> Path:
    """Export the talking head of ``syn`` with its avatar ``metadata`` (the synthesis file's:
    ``avatar_neutral``, ``shape_pca``, ``background_jpeg``; :mod:`facesynth.onnx.avatar`) to
    one ONNX file, written atomically. Returns the path."""
    path = Path(path)
    metadata = {"landmark_scheme": str(getattr(syn, "scheme", "ibug68")), **metadata}
    graph = TalkingHeadGraph(syn, Avatar(metadata, str(path)), feather).eval()
    n = np.asarray(metadata["avatar_neutral"], np.float32)
    example = (torch.from_numpy(np.stack([n + 1.5, n * 1.01 - 2.0])), torch.from_numpy(n + 0.5))
    h, w = graph.frame_warp.frame_size
    meta = {k: v for k, v in metadata.items() if k not in ("format", "inputs", "outputs")}  # the model's provenance too
    meta.update({"facesynth_version": __version__, "format": TALKING_HEAD_FORMAT, "frame_size": [w, h],
                 "feather": graph.feather, "opset": opset, "output_layout": TALKING_HEAD_LAYOUT, "n_landmarks": int(n.shape[0])})
    meta.pop("int32_index_gathers", None)  # the synthesis graph's count, not this one's
    save_graph(graph, example, path, INPUTS, OUTPUTS, meta, opset,
               "facesynth talking head: driver landmarks, driver neutral -> avatar frame")
    return path


def check_talking_head(syn, metadata: dict, path: str | os.PathLike, frames: int = 4, tol: int = 2) -> int:
    """Run the talking-head file ``path`` in ONNX Runtime and its graph in torch on ``frames``
    driver frames made from the avatar's own neutral (the neutral as the driver's neutral;
    the frames moved, turned and scaled a little). Returns the largest pixel difference (0-255);
    FacesynthError above ``tol`` (with an int8 basis, plus on a frame the pixels that its
    codes on a rounding tie may move it by: the int8 parity contract,
    :func:`facesynth.onnx.synthesis.torch_reference`) or when the avatar landmarks differ by
    more than 0.01 px."""
    from facesynth.runtime.talking_head import TalkingHead

    metadata = {"landmark_scheme": str(getattr(syn, "scheme", "ibug68")), **metadata}
    n = np.asarray(metadata["avatar_neutral"], np.float32)
    th = TalkingHead(path, driver_neutral=n)
    graph = TalkingHeadGraph(syn, Avatar(metadata, str(path)), th.feather).eval()
    c = n.mean(0)
    driver = []
    for k in range(frames):
        a, s = 0.04 * (k - frames / 2), 1.0 + 0.02 * k
        rot = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]], np.float32)
        driver.append((n - c) @ rot.T + c + np.float32(3 * k))
    driver = np.stack(driver).astype(np.float32)
    got, got_lm = th.run(driver)
    # the int8 parity contract: a code on a rounding tie may move its frame by one code step
    feeds = dict(zip(TALKING_HEAD_INPUTS, (driver, n), strict=True))
    (want, want_lm), allowance = torch_reference(graph, syn.appearance, path, feeds, 0.0)
    per_frame = np.abs(got.astype(int) - want).reshape(len(got), -1).max(1)
    frame_tol = tol + np.ceil(255 * np.asarray(allowance))
    worst = int(per_frame.max())
    lm_diff = float(np.abs(got_lm - want_lm).max())
    if (per_frame > frame_tol).any() or not lm_diff <= 0.01:
        raise FacesynthError(f"{path}: ONNX Runtime and torch differ by {worst}/255 (> {int(np.max(frame_tol))}) or the "
                             f"avatar landmarks by {lm_diff:.3g} px")
    return worst
