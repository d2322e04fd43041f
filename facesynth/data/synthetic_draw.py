"""Drawing helpers of the synthetic subject: anti-aliased coverage masks, in-place
blending on bounding boxes, and per-pixel face coordinates for one frame."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from facesynth.geometry import invert_affine

_SS = 16  # sub-pixel factor for cv2 drawing (shift=4)
HEAD_BOX = [[-0.62, -0.36], [0.62, -0.36], [-0.62, 1.32], [0.62, 1.32]]  # face units: hair, ears, face, jaw open


def bbox(alpha: np.ndarray) -> tuple[slice, slice] | None:
    rows = np.flatnonzero(alpha.any(1))
    if not len(rows):
        return None
    cols = np.flatnonzero(alpha.any(0))
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


class Alpha(NamedTuple):
    """Coverage (H, W) float32 in [0, 1], zero outside the slices ``s``."""

    a: np.ndarray
    s: tuple[slice, slice]


class Shaded(NamedTuple):
    """A colour (3,) times a shading map (H, W, 1), evaluated only where it is drawn."""

    rgb: np.ndarray
    shade: np.ndarray


def blend(img: np.ndarray, alpha: Alpha | np.ndarray, color, k: float = 1.0) -> None:
    """img <- img + k alpha (color - img) in place, on alpha's bounding box only.

    alpha: an ``Alpha`` or an (H, W) array; color (3,) or (H, W, 3)."""
    if isinstance(alpha, Alpha):
        s, a = alpha.s, alpha.a[alpha.s]
    else:
        s = bbox(alpha)
        if s is None:
            return
        a = alpha[s]
    if a.size == 0:
        return
    if isinstance(color, Shaded):
        col = color.rgb * color.shade[s]
    else:
        col = color[s] if np.ndim(color) == 3 else color
    sub = img[s]
    sub += (a * k)[..., None] * (col - sub)


class DrawFrame:
    """Per-frame drawing context: image-space canvas plus face coordinates per pixel."""

    def __init__(self, size: int, m: np.ndarray, grid: np.ndarray):
        self.size = size
        self.m = m
        self.ppu = float(np.hypot(m[0, 0], m[1, 0]))  # pixels per face unit
        self.angle = float(np.arctan2(m[1, 0], m[0, 0]))
        # face coordinates of each pixel, computed on the head's box only (zero elsewhere)
        self.head = self.box(HEAD_BOX, 0.02)
        inv = invert_affine(m[None])[0]
        self.U = np.zeros((size, size), np.float32)
        self.V = np.zeros((size, size), np.float32)
        gx, gy = grid[0][self.head], grid[1][self.head]
        self.U[self.head] = inv[0, 0] * gx + inv[0, 1] * gy + inv[0, 2]
        self.V[self.head] = inv[1, 0] * gx + inv[1, 1] * gy + inv[1, 2]

    def to_img(self, pts: np.ndarray) -> np.ndarray:
        return pts @ self.m[:, :2].T + self.m[:, 2]

    def box(self, pts_local, margin: float) -> tuple[slice, slice]:
        """Image slices covering points given in face units, plus a margin (face units)."""
        p = self.to_img(np.atleast_2d(np.asarray(pts_local, dtype=np.float64)))
        lo = np.floor(p.min(0) - margin * self.ppu - 1).astype(int).clip(0, self.size)
        hi = np.ceil(p.max(0) + margin * self.ppu + 2).astype(int).clip(0, self.size)
        return slice(lo[1], hi[1]), slice(lo[0], hi[0])

    def _alpha(self, mask: np.ndarray, s: tuple[slice, slice]) -> Alpha:
        out = np.zeros((self.size, self.size), np.float32)
        out[s] = mask[s] * np.float32(1.0 / 255.0)
        return Alpha(out, s)

    def poly(self, pts_local: np.ndarray) -> Alpha:
        """Anti-aliased coverage of a filled polygon given in face units."""
        mask = np.zeros((self.size, self.size), np.uint8)
        p = np.round(self.to_img(pts_local) * _SS).astype(np.int32)
        cv2.fillPoly(mask, [p], 255, cv2.LINE_AA, shift=4)
        return self._alpha(mask, self.box(pts_local, 0.0))

    def line(self, pts_local: np.ndarray, width_units: float, blur: float = 0.0) -> Alpha:
        """Anti-aliased coverage of an open polyline (width in face units), optionally blurred."""
        mask = np.zeros((self.size, self.size), np.uint8)
        p = np.round(self.to_img(pts_local) * _SS).astype(np.int32)
        cv2.polylines(mask, [p], False, 255, max(1, int(round(width_units * self.ppu))), cv2.LINE_AA, shift=4)
        s = self.box(pts_local, width_units + 3.5 * blur)
        out = self._alpha(mask, s)
        if blur > 0:
            out.a[s] = cv2.GaussianBlur(out.a[s], (0, 0), blur * self.ppu, borderType=cv2.BORDER_CONSTANT)
        return out

    def shade_blob(self, img: np.ndarray, amount: float, cx: float, cy: float, sx: float, sy: float | None = None,
                   mask: np.ndarray | None = None) -> None:
        """Multiply ``img`` by (1 - amount * Gaussian blob) (negative amount brightens), within 3 sigma."""
        sy = sx if sy is None else sy
        s = self.box([[cx - 3 * sx, cy - 3 * sy], [cx + 3 * sx, cy + 3 * sy], [cx - 3 * sx, cy + 3 * sy],
                      [cx + 3 * sx, cy - 3 * sy]], 0.0)
        b = np.exp(-0.5 * (((self.U[s] - cx) / sx) ** 2 + ((self.V[s] - cy) / sy) ** 2))
        if mask is not None:
            b *= mask[s]
        img[s] *= (1.0 - amount * b)[..., None]


def bezier(p0, p1, p2, n: int = 16) -> np.ndarray:
    t = np.linspace(0, 1, n)[:, None]
    return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2
