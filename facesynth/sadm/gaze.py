"""SADM's gaze path: iris positions in each eye's own frame -> a correction of b_g.

Landmarks of the eye lids and corners do not say where the eye looks; a landmark scheme
with irises (``ibug68+iris``, ``mediapipe478``) does. Four numbers per frame carry it (per
eye, the iris centre c relative to the eye corners a, b: origin at their midpoint m, x along
e = b - a, y along e rotated by +90 degrees in image axes (x right, y down), both divided by
|e|; "a" is the corner on the image-left side, so x grows towards image right for both eyes):

    g_x = (c - m) . e / |e|^2,   g_y = (c - m) . perp(e) / |e|^2

They are invariant to similarity transforms of the frame, so frame landmarks suffice.

Two ways to use them (``SADMConfig.gaze_mode``), both by default (``both``):

* **gaze inputs** (``inside``, :class:`GazeInputs`): the 4 features (in pixels of a
  100-px face, :data:`INPUT_SCALE`) appended ``gaze_copies`` times (default 4) to the main
  regressor's inputs, so that its kernel sees gaze jointly with the eye-lid points;
* **the gaze path** (``path``, :class:`GazePath`): a few strong inputs drown in a kernel
  over many, so gaze gets its own path: a ridge regression from the features, their
  squares and pairwise products (4 + 10 = 14 inputs, z-scored) to the residual of the main
  regressor's prediction, added to it. ``gaze_target="eyes"`` (default): the residual
  *texture* of the eye region (iBUG eye polygons dilated 3 px; the correction is zero
  elsewhere); ``"params"``: the residual b_g (every pixel; it learned correlations outside
  the eyes that cost 0.2 dB on a real clip, docs/sadm.md "Gaze").

The path's details:

* Residuals are **cross-fitted** (``gaze_folds`` contiguous blocks of the training segment:
  the main regressor refitted without a block predicts that block), because a kernel
  regressor's in-sample residuals are shrunk towards 0 (it partly memorises each training
  frame's appearance, gaze included) and a ridge on them would learn too little;
  ``gaze_folds=0`` uses the in-sample residuals (cheaper).
* alpha (relative to the number of rows: lambda = alpha * N on z-scored inputs) is chosen
  from :data:`ALPHAS` by blocked cross-validation over the same folds, by the summed squared
  error of all outputs, then the ridge is refitted on every training row.
* Noisy landmark copies (SADM's augmentation) enter the ridge's design as they enter the
  main regressor's, so that landmark noise on the irises shrinks the weights rather than
  being amplified at test time.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import nn

from facesynth.errors import FacesynthError
from facesynth.landmarks import LandmarkScheme

TARGETS = ("params", "eyes")
ALPHAS = (1e-3, 1e-2, 0.1, 1.0, 10.0)
"""Relative ridge strengths tried by the blocked cross-validation (lambda = alpha * N)."""
FEATURE_NAMES = ("right_x", "right_y", "left_x", "left_y")
INPUT_SCALE = 30.0
"""Eye widths -> pixels of a 100-px-wide face (an eye's corner distance is ~30 % of the face
width), the unit of SADM's ``landmarks`` features."""


def has_irises(scheme: LandmarkScheme) -> bool:
    return "iris_centres" in scheme.regions and "eye_corners" in scheme.regions


def _pairs(n: int) -> tuple[list[int], list[int]]:
    i, j = np.triu_indices(n)
    return i.tolist(), j.tolist()


class GazeFeatures(nn.Module):
    """Frame landmarks (B, P, 2) -> gaze features (B, 4): right eye (x, y), left eye (x, y).

    ``corners``: the scheme's eye corners in iBUG order (right eye outer, inner; left eye
    inner, outer), ``centres``: the iris centres (right, left).
    """

    def __init__(self, scheme: LandmarkScheme):
        super().__init__()
        if not has_irises(scheme):
            raise FacesynthError(f"landmark scheme {scheme.name!r} has no irises: no gaze features")
        c = [int(v) for v in scheme.region("eye_corners")]
        self.scheme = scheme.name
        self.first = [c[0], c[2]]  # image-left corner of each eye (right eye outer, left eye inner)
        self.second = [c[1], c[3]]
        self.centres = [int(v) for v in scheme.region("iris_centres")]

    def forward(self, landmarks: torch.Tensor) -> torch.Tensor:
        a, b, c = landmarks[:, self.first], landmarks[:, self.second], landmarks[:, self.centres]  # (B, 2, 2)
        e = b - a
        d = c - 0.5 * (a + b)
        n2 = (e * e).sum(-1)
        gx = (d * e).sum(-1) / n2
        gy = (d[..., 1] * e[..., 0] - d[..., 0] * e[..., 1]) / n2  # d . (-e_y, e_x)
        return torch.stack([gx, gy], -1).reshape(landmarks.shape[0], 4)


def expand(f: np.ndarray | torch.Tensor):
    """Features (B, F) -> (B, F + F (F + 1) / 2): themselves, then their squares and pairwise products."""
    i, j = _pairs(f.shape[1])
    if isinstance(f, torch.Tensor):
        return torch.cat([f, f[:, i] * f[:, j]], 1)
    return np.concatenate([f, f[:, i] * f[:, j]], 1)


class GazePath(nn.Module):
    """Landmarks (B, P, 2) -> a correction (B, K): ridge on the z-scored expanded gaze features.

    ``target`` says what it corrects: ``"params"``, b_g (K = K_g, added before b_g's clamp),
    or ``"eyes"``, the reference-frame texture (K = C M, channel-major, zero outside the eye
    region: added to the texture by :meth:`add_to`). Built by :func:`fit_gaze_path` or from a
    state dict (``mu``, ``sd``, ``weight``, ``bias``; the saved form keeps the full width).

    An ``"eyes"`` path also holds the compact form of its weights, built here from the
    columns where ``weight`` or ``bias`` is nonzero (non-persistent buffers, so artifacts of
    either age load the same): ``eye_columns`` (N,) int64, ``eye_weight`` (E, N),
    ``eye_bias`` (N,). :meth:`add_to` computes only those N columns (a few percent of C M)
    and adds them in place of a dense (E, C M) matmul whose other columns are zero; the sum
    at every element is the same single addition, so the texture is unchanged.
    """

    def __init__(self, scheme: LandmarkScheme, mu: torch.Tensor, sd: torch.Tensor, weight: torch.Tensor,
                 bias: torch.Tensor, alpha: float = float("nan"), target: str = "params"):
        super().__init__()
        if target not in TARGETS:
            raise FacesynthError(f"sadm.gaze_target must be one of {TARGETS}, got {target!r}")
        self.target = target
        self.features = GazeFeatures(scheme)
        self.register_buffer("mu", mu.float())  # (E,)
        self.register_buffer("sd", sd.float())  # (E,)
        self.register_buffer("weight", weight.float())  # (E, K)
        self.register_buffer("bias", bias.float())  # (K,)
        self.alpha = float(alpha)
        if target == "eyes":
            self._compact()

    def _compact(self) -> None:
        """The nonzero columns of an ``"eyes"`` path's weights (see the class docstring)."""
        cols = torch.nonzero((self.weight != 0).any(0) | (self.bias != 0)).reshape(-1)
        self.register_buffer("eye_columns", cols, persistent=False)  # (N,) into C M
        self.register_buffer("eye_weight", self.weight[:, cols].contiguous(), persistent=False)  # (E, N)
        self.register_buffer("eye_bias", self.bias[cols].contiguous(), persistent=False)  # (N,)

    def standardized(self, landmarks: torch.Tensor) -> torch.Tensor:
        """(B, E) z-scored expanded gaze features of frame landmarks (B, P, 2)."""
        return (expand(self.features(landmarks)) - self.mu) / self.sd

    def forward(self, landmarks: torch.Tensor) -> torch.Tensor:
        return torch.matmul(self.standardized(landmarks), self.weight) + self.bias

    def add_to(self, texture: torch.Tensor, landmarks: torch.Tensor) -> torch.Tensor:
        """``texture + self(landmarks)`` for an ``"eyes"`` path, (B, C M) -> (B, C M), from the
        compact weights: the N eye columns are computed and scatter-added (one ONNX
        ScatterElements with reduction "add"); every other element is returned unchanged."""
        corr = torch.matmul(self.standardized(landmarks), self.eye_weight) + self.eye_bias  # (B, N)
        index = torch.zeros_like(corr, dtype=torch.int64) + self.eye_columns
        return texture.scatter_add(1, index, corr)

    def summary(self) -> dict:
        return {"inputs": FEATURE_NAMES, "expanded": int(self.mu.shape[0]), "outputs": int(self.bias.shape[0]),
                "alpha": self.alpha, "scheme": self.features.scheme, "target": self.target}

    def select_outputs(self, keep: np.ndarray) -> "GazePath":
        """A copy predicting only outputs ``keep`` (appearance compression)."""
        k = torch.as_tensor(np.asarray(keep, np.int64))
        out = GazePath.__new__(GazePath)
        nn.Module.__init__(out)
        out.features, out.alpha, out.target = self.features, self.alpha, self.target
        for name in ("mu", "sd"):
            out.register_buffer(name, getattr(self, name))
        out.register_buffer("weight", self.weight[:, k].contiguous())
        out.register_buffer("bias", self.bias[k].contiguous())
        if out.target == "eyes":
            out._compact()
        return out

    @classmethod
    def from_state(cls, scheme: LandmarkScheme, state: dict, alpha: float = float("nan"), target: str = "params") -> "GazePath":
        return cls(scheme, state["mu"], state["sd"], state["weight"], state["bias"], alpha, target)


class GazeInputs(nn.Module):
    """Gaze features as extra main-regressor inputs (``sadm.gaze_mode=inside``): landmarks
    (B, P, 2) -> (B, 4 * copies), the 4 features times :data:`INPUT_SCALE` repeated ``copies``
    times (a z-scoring kernel then weighs them sqrt(copies) times as much as one landmark
    coordinate; the scale gives regressors that do not standardise, e.g. the linear ridge,
    inputs of the landmark features' magnitude)."""

    def __init__(self, scheme: LandmarkScheme, copies: int = 1):
        super().__init__()
        if copies < 1:
            raise FacesynthError(f"sadm.gaze_copies must be >= 1, got {copies}")
        self.features = GazeFeatures(scheme)
        self.copies = int(copies)

    def forward(self, landmarks: torch.Tensor) -> torch.Tensor:
        f = self.features(landmarks) * INPUT_SCALE
        return f if self.copies == 1 else f.repeat(1, self.copies)


def gaze_features(scheme: LandmarkScheme, landmarks: np.ndarray) -> np.ndarray:
    """(N, P, 2) frame landmarks -> (N, 4) float64 gaze features (as :class:`GazeFeatures`)."""
    with torch.no_grad():
        return GazeFeatures(scheme)(torch.from_numpy(np.asarray(landmarks, np.float64))).numpy()


def ridge_fit(z: np.ndarray, r: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form ridge on centred data, unpenalised intercept: z (N, E), r (N, K) ->
    weight (E, K), bias (K,) with r ~ z @ weight + bias."""
    mz, mr = z.mean(0), r.mean(0)
    zc = z - mz
    w = np.linalg.solve(zc.T @ zc + lam * np.eye(z.shape[1]), zc.T @ (r - mr))
    return w, mr - mz @ w


def fit_gaze_path(scheme: LandmarkScheme, landmarks: np.ndarray, residuals: np.ndarray, groups: np.ndarray,
                  alphas=ALPHAS, columns: np.ndarray | None = None, n_out: int | None = None,
                  target: str = "params") -> GazePath:
    """Fit the gaze path.

    Parameters
    ----------
    landmarks : (N, P, 2) frame landmarks of the design rows (clean and noisy copies)
    residuals : (N, K) what the path learns for those rows: b_g minus the main regressor's
        prediction, or (``columns``) that residual's texture at the output columns ``columns``
        of ``n_out`` (the eye region; the path's weights are zero elsewhere)
    groups : (N,) int fold of each row (contiguous blocks of the training segment; a noisy
        copy has its frame's fold); alpha is chosen by leave-one-fold-out squared error
        (with a single fold no choice can be made: the middle of ``alphas`` is used)
    """
    x = expand(gaze_features(scheme, landmarks))
    r = np.asarray(residuals, np.float64)
    if not (np.isfinite(x).all() and np.isfinite(r).all()):
        raise FacesynthError("gaze path: non-finite gaze features or residuals (degenerate eye corners?)")
    mu, sd = x.mean(0), x.std(0)
    sd = np.where(sd > 1e-12, sd, 1.0)
    z = (x - mu) / sd
    folds = np.unique(groups)
    if len(folds) > 1:
        err = []
        for a in alphas:
            e = 0.0
            for f in folds:
                tr, te = groups != f, groups == f
                w, b = ridge_fit(z[tr], r[tr], a * tr.sum())
                e += float(((z[te] @ w + b - r[te]) ** 2).sum())
            err.append(e)
        alpha = float(alphas[int(np.argmin(err))])
    else:
        alpha = float(alphas[len(alphas) // 2])
    w, b = ridge_fit(z, r, alpha * len(z))
    if columns is not None:
        w_full, b_full = np.zeros((w.shape[0], n_out)), np.zeros(n_out)
        w_full[:, columns], b_full[columns] = w, b
        w, b = w_full, b_full
    t = torch.from_numpy
    return GazePath(scheme, t(mu), t(sd), t(w), t(b), alpha, target)


def eye_columns(model, scheme: LandmarkScheme, dilate: int = 3) -> np.ndarray:
    """int64 texture columns (channel-major, C M) of the eye region of ``model``'s reference
    frame: the polygons of ``scheme``'s (the face model's scheme) ``right_eye`` and
    ``left_eye`` dilated by ``dilate`` px (ibug68: the eye region of docs/sadm.md's breakdown)."""
    ref = model.reference
    h, w = ref.size
    index = model.sampler().mask_index.numpy()
    m = np.zeros((h, w), np.uint8)
    for eye in ("right_eye", "left_eye"):
        cv2.fillPoly(m, [np.round(ref.points[scheme.region(eye)]).astype(np.int32)], 1)
    m = cv2.dilate(m, np.ones((2 * dilate + 1,) * 2, np.uint8)).reshape(-1)[index].astype(bool)
    cols = np.flatnonzero(m)
    return np.concatenate([c * len(index) + cols for c in range(model.n_channels)]).astype(np.int64)
