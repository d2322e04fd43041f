"""Landmark denoising by the training shapes' subspace, as a torch module (the graph form
of :meth:`facesynth.model.face_model.FaceModel.denoise`).

Landmarks are similarity-aligned to the model's mean shape, projected on a PCA of the
aligned training shapes (keeping ``denoise_variance`` of their variance) and mapped back to
the frame. Independent per-point jitter spreads over all 2P coordinates while the face
moves in a few dozen directions, so the projection keeps about K / 2P of the noise power
(478 points: ~48 of 956) and almost all of the motion seen in training. Both the regressor's
input and the warp target read the denoised landmarks.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from facesynth.model.pca import PCAModel
from facesynth.model.warp import apply_affine_t, invert_affine_t, similarity_to


class ShapeDenoiser(nn.Module):
    """Forward: landmarks (B, P', 2) frame pixels -> (B, P', 2): the face model's P points
    (the first ones) projected, any points beyond them (the irises of ``ibug68+iris``) as given."""

    def __init__(self, pca: PCAModel):
        super().__init__()
        mean = np.asarray(pca.mean, np.float32)
        self.register_buffer("mean_shape", torch.from_numpy(mean.reshape(-1, 2).copy()))  # (P, 2)
        self.register_buffer("mean", torch.from_numpy(mean.copy()))  # (2P,)
        self.register_buffer("down", torch.from_numpy(np.asarray(pca.components, np.float32).T.copy()))  # (2P, K)
        self.register_buffer("up", torch.from_numpy(np.asarray(pca.components, np.float32).copy()))  # (K, 2P)

    def forward(self, landmarks: torch.Tensor) -> torch.Tensor:
        n = self.mean_shape.shape[0]
        pts = landmarks[:, :n] if landmarks.shape[1] > n else landmarks
        m = similarity_to(pts, self.mean_shape)
        x = apply_affine_t(pts, m).flatten(1) - self.mean
        proj = torch.matmul(torch.matmul(x, self.down), self.up) + self.mean
        out = apply_affine_t(proj.reshape(pts.shape), invert_affine_t(m))
        return out if landmarks.shape[1] == n else torch.cat([out, landmarks[:, n:]], 1)


def shape_denoiser(pca: PCAModel | None) -> nn.Module:
    """:class:`ShapeDenoiser` of ``pca``, or the identity when there is none."""
    return nn.Identity() if pca is None else ShapeDenoiser(pca)


def denoise_model(aligned: np.ndarray, variance: float, free: np.ndarray) -> PCAModel:
    """The denoiser's subspace over (N, P, 2) aligned training shapes: their PCA keeping
    ``variance``, widened by every coordinate of the ``free`` points (an orthonormal basis of
    both), so that the projection leaves those points as they are and fits the PCA's modes
    to the others. Eigenvalues: the training shapes' variance along each basis vector."""
    x = aligned.reshape(len(aligned), -1).astype(np.float64)
    pca = PCAModel.fit(x, None, variance)
    if len(free) == 0:
        return pca
    cols = np.stack([2 * np.asarray(free), 2 * np.asarray(free) + 1], 1).reshape(-1)
    unit = np.zeros((len(cols), x.shape[1]))
    unit[np.arange(len(cols)), cols] = 1.0
    q, _ = np.linalg.qr(np.concatenate([pca.components.astype(np.float64), unit]).T)  # (2P, K + 2F)
    comps = q.T.astype(np.float32)
    ev = ((x - pca.mean) @ comps.T.astype(np.float64)).var(0, ddof=1)
    return PCAModel(pca.mean, comps, ev, pca.total_variance)
