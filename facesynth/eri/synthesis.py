"""Expression synthesis on a target face B with an ERI model, in five steps:

1. warp B's neutral image once to the model's neutral geometry -> B_temp (3, M);
2. predict eigenERI coefficients from the FAPs (SVR bank) and reconstruct R';
3. B' = R' x B_temp per pixel and channel;
4. B's new feature positions from the FAPs and *B's* FAPUs (``faps_to_landmarks``);
   warp B' onto them (``facesynth.model.warp.ToTarget``);
5. paste into B's frame (``facesynth.sadm.synthesis.composite``).

Steps 2-5 run on batches of frames. ``mode="geometry"`` skips steps 2-3 (R' = 1): the
geometry-only baseline.
"""

from __future__ import annotations

from typing import Iterator

import cv2
import numpy as np
import torch

from facesynth.compositing import composite
from facesynth.eri.faps import faps_to_landmarks
from facesynth.eri.geometry import extend, forehead_points, to_canvas
from facesynth.eri.model import EriModel
from facesynth.eri.ratio import apply_ratio, edge_confidence, sample_textures, to_multiplier
from facesynth.errors import FacesynthError
from facesynth.geometry import apply_affine, invert_affine
from facesynth.model.warp import ToTarget, candidate_spans

MODES = ("eri", "geometry")


class EriSynthesizer:
    """Drive a target face with FAPs.

    Parameters
    ----------
    model : EriModel
    image : uint8 (H, W, 3), the target's neutral image B
    landmarks : (68, 2), B's landmarks (frame pixels)
    variant : SVR variant (default: the model's driver)
    raw : bool
        Use the predicted ratios as they are: no edge confidence, no brightening cap
        (``config.edge_tau``, ``config.max_brighten``; these guard cross-subject transfer).
    """

    def __init__(self, model: EriModel, image: np.ndarray, landmarks: np.ndarray, variant: str | None = None, raw: bool = False):
        if model.pca is None or not model.regressors:
            raise FacesynthError("ERI model is not fitted (no eigenERI PCA / regressors)")
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise FacesynthError(f"target image must be uint8 (H, W, 3) RGB, got {img.dtype} {img.shape}")
        self.model, self.image, self.variant, self.raw = model, img, variant or model.driver, raw
        self.neutral = np.asarray(landmarks, np.float32).reshape(68, 2)
        cfg = model.config
        self.forehead = forehead_points(self.neutral, cfg.forehead) if len(model.forehead) else np.zeros((0, 2))
        # Step 1: B -> model geometry, once.
        self.base = sample_textures(img[None], self.extend(self.neutral[None]), model.sampler())[0]
        self.pad = int(round(0.3 * max(model.reference.size)))
        h, w = model.reference.size
        self.canvas = (h + 2 * self.pad, w + 2 * self.pad)
        self._warp: tuple[bytes, ToTarget] | None = None

    def extend(self, landmarks: np.ndarray) -> np.ndarray:
        return extend(landmarks, self.neutral, self.forehead)

    # ------------------------------------------------------------------ steps
    def ratio(self, faps: np.ndarray, coefficients: np.ndarray | None = None) -> torch.Tensor:
        """Step 2: R' (N, 3, M) from FAPs (or from given eigenERI coefficients)."""
        m = self.model
        b = m.predict_coefficients(faps, self.variant) if coefficients is None else np.asarray(coefficients, np.float32)
        vals = torch.from_numpy(m.pca.reconstruct(b)).reshape(len(b), 3, -1)
        if self.raw:
            return to_multiplier(vals, m.config.log, m.config.clip)
        if "_confidence" not in self.__dict__:
            self._confidence = edge_confidence(torch.from_numpy(m.neutral_texture), m.sampler(), m.config.edge_tau)
        return to_multiplier(vals, m.config.log, m.config.clip, self._confidence, m.config.max_brighten)

    def textures(self, faps: np.ndarray, mode: str = "eri", coefficients: np.ndarray | None = None) -> torch.Tensor:
        """Steps 2-3: B' (N, 3, M) in the model geometry (``mode="geometry"``: B_temp)."""
        if mode not in MODES:
            raise FacesynthError(f"mode must be one of {MODES}, got {mode!r}")
        n = len(faps) if coefficients is None else len(coefficients)
        if mode == "geometry":
            return self.base.unsqueeze(0).expand(n, -1, -1)
        return apply_ratio(self.ratio(faps, coefficients), self.base, self.model.config.eps)

    def positions(self, faps: np.ndarray, poses: np.ndarray | None = None) -> np.ndarray:
        """Step 4a: B's expressive landmarks (N, 68, 2) from FAPs and B's FAPUs, in B's head
        pose, or moved by ``poses`` (N, 2, 3) (neutral -> frame similarity transforms)."""
        lm = faps_to_landmarks(self.neutral, faps)
        return lm if poses is None else apply_affine(lm.astype(np.float64), poses).astype(np.float32)

    def warp(self, textures: torch.Tensor, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Step 4b: warp (N, 3, M) textures onto (N, 68, 2) landmarks.

        Returns crop float32 (N, Hc, Wc, 3), mask float32 (N, Hc, Wc), placement (N, 2, 3).
        """
        ext = self.extend(landmarks)
        canvas, m = to_canvas(ext, self.model.reference.points, self.pad)
        span = np.maximum(self.model.span, candidate_spans(self.model.reference, canvas, 1.1))
        if self._warp is None or self._warp[0] != span.tobytes():
            self._warp = (span.tobytes(), ToTarget(self.model.reference, span, self.canvas))
        with torch.no_grad():
            img, mask = self._warp[1](textures.float(), torch.from_numpy(canvas))
        return img.permute(0, 2, 3, 1).numpy(), mask[:, 0].numpy(), invert_affine(m)

    def render(
        self, faps: np.ndarray, mode: str = "eri", backgrounds: np.ndarray | None = None, poses: np.ndarray | None = None,
        coefficients: np.ndarray | None = None, feather: float | None = None, positions: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Steps 2-5 for a batch: (N, 36) FAPs -> frames uint8 (N, H, W, 3) and face masks
        bool (N, H, W) (pixels fully inside the rendered face).

        ``backgrounds`` (N, H, W, 3) default to B's image; ``poses`` as in :meth:`positions`;
        ``positions`` (N, 68, 2): B's landmarks given directly (e.g. the driver's landmarks
        retargeted onto B, :class:`facesynth.retarget.Retargeter`) instead of from the FAPs.
        """
        faps = np.asarray(faps, np.float32)
        tex = self.textures(faps, mode, coefficients)
        pos = self.positions(faps, poses) if positions is None else np.asarray(positions, np.float32)
        crop, mask, place = self.warp(tex, pos)
        feather = self.model.config.feather if feather is None else feather
        frames, masks = [], []
        for i in range(len(faps)):
            bg = self.image if backgrounds is None else backgrounds[i]
            frames.append(composite(crop[i], mask[i], place[i], bg, feather))
            h, w = bg.shape[:2]
            masks.append(cv2.warpAffine(mask[i], place[i], (w, h), flags=cv2.INTER_LINEAR) > 0.999)
        return np.stack(frames), np.stack(masks)

    def iter_render(self, faps: np.ndarray, mode: str = "eri", batch_size: int | None = None,
                    positions: np.ndarray | None = None, background=None) -> Iterator[np.ndarray]:
        """Yield uint8 (H, W, 3) frames of B driven by (N, 36) FAPs, in batches
        (``positions``: as in :meth:`render`). ``background``, optional: B's landmarks (68, 2)
        of a frame -> its uint8 (H, W, 3) background (e.g. B's image warped so that its head
        follows the face, :class:`facesynth.runtime.fullframe.FrameWarp`); default B's image."""
        bs = batch_size or self.model.config.batch_size
        for s in range(0, len(faps), bs):
            f = faps[s : s + bs]
            pos = self.positions(np.asarray(f, np.float32)) if positions is None else positions[s : s + bs]
            bgs = None if background is None else np.stack([background(p) for p in pos])
            yield from self.render(f, mode, backgrounds=bgs, positions=pos)[0]
