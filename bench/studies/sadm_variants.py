"""The SADM variant study of docs/sadm.md ("Second study"): every variant scored on the
validation slice AND the test segment of each clip, at landmark noise sigma 0 and 2.

Protocol (as ``train.py`` / ``facesynth evaluate``): per clip one face model fitted on the
training segment (first 75 %); **val** = fit on the first 85 % of the training segment,
score on its last 15 %; **test** = fit on the whole training segment, score on the test
segment. Reference-frame PSNR (peak 255, over the mask) of the clamped prediction;
landmark noise seeded as in :mod:`facesynth.eval.sadm_eval` and added before anything
else (temporal filters included); 4 noisy training copies at 1 px unless a variant says.

    python -m bench.studies.sadm_variants [--clips lp_d6,lp_d10,lp_d3] [--only krr_rbf,krr_matern]

Prints ONE JSON line: ``{variant: {clip: {"val": [psnr_sigma0, loss_0_to_2], "test": [...]}}}``
(``--list`` prints the variant names). All variants: ~10 min on one core.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import scipy.linalg
import torch

from facesynth.data import load_sequence, shared_clip, temporal_split
from facesynth.eval.sadm_eval import noisy_landmarks
from facesynth.metrics import psnr
from facesynth.model import FaceModel, FaceModelConfig
from facesynth.regressors import CONFIGS, REGISTRY
from facesynth.regressors.linear import LinearConfig, LinearRegressor
from facesynth.runtime.filters import smooth_landmarks
from facesynth.sadm.synthesis import RIGID_POINTS, ShapeFeatures


def _kernel(kind: str, d2: np.ndarray) -> np.ndarray:
    """Kernel values of scaled squared distances ``d2`` (gamma and width applied)."""
    r = np.sqrt(d2)
    if kind == "rbf":
        return np.exp(-d2)
    if kind == "laplacian":
        return np.exp(-r)
    if kind == "matern32":
        return (1 + np.sqrt(3) * r) * np.exp(-np.sqrt(3) * r)
    if kind == "matern52":
        return (1 + np.sqrt(5) * r + 5 / 3 * r * r) * np.exp(-np.sqrt(5) * r)
    if kind == "rq":
        return 1.0 / (1 + d2 / 2)
    raise KeyError(kind)


class Clip:
    def __init__(self, name: str):
        seq = load_sequence(shared_clip(name))
        self.name, self.lm = name, seq.landmarks
        self.tr, self.te = temporal_split(len(seq), 0.75)
        self.model, self.tex_tr = FaceModel.fit_with_textures(seq, FaceModelConfig(), rows=self.tr, progress=False)
        self.tex_te = self.model.sample_textures(seq, self.te)
        self.y_tr = self.model.appearance_params(self.tex_tr)
        n_val = int(round(len(self.tr) * 0.15))
        self.fit, self.val = np.arange(len(self.tr) - n_val), np.arange(len(self.tr) - n_val, len(self.tr))
        self.lim = self.model.config.clamp_k * np.sqrt(self.model.appearance_pca.eigenvalues)

    def split(self, mode):
        if mode == "val":
            return self.tr[self.fit], self.y_tr[self.fit], self.tr[self.val], self.tex_tr[self.val]
        return self.tr, self.y_tr, self.te, self.tex_te

    def feats(self, lm, kind="landmarks"):
        return ShapeFeatures.numpy(self.model, lm, kind, True).astype(np.float64)

    def score(self, b, tex):
        """PSNR of predicted b_g (N, K_g) -- or of predicted textures (N, C*M) -- vs ``tex``."""
        t = b if b.shape[1] == tex.shape[1] else self.model.texture_from_params(np.clip(b, -self.lim, self.lim))
        return psnr(np.clip(t, 0, 1) * 255.0, np.clip(tex, 0, 1) * 255.0)


def copies(lm, sigma=1.0, n=4, seed=0):
    """[clean, noisy copy 1..n] of the (T, 68, 2) training stream (each copy kept in time order)."""
    rng = np.random.default_rng(seed)
    return [lm] + [lm + rng.normal(0, sigma, lm.shape).astype(np.float32) for _ in range(n if sigma > 0 else 0)]


class KRR:
    """Kernel ridge (kernel on z-scored inputs, gamma = gamma_mult / D, optional per-input
    weights) blended with a linear ridge map; inputs clipped to the training box."""

    def __init__(self, alpha=0.5, gamma_mult=0.3, ridge=10.0, blend=0.5, kernel="matern32", zscore=True,
                 weights=None, gamma=None, widths=(1.0,)):
        self.__dict__.update({k: v for k, v in locals().items() if k != "self"})

    def k(self, a, b):
        d2 = np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T, 0) * self.g
        out = 0.0
        for w in self.widths:
            out = out + _kernel(self.kernel, d2 * w)
        return out / len(self.widths)

    def z(self, x):
        z = (np.clip(x, self.lo, self.hi) - self.mx) / self.sx
        return z if self.weights is None else z * self.weights

    def fit(self, x, y, xl=None):
        xl = x if xl is None else xl
        self.lo, self.hi, self.mx = x.min(0), x.max(0), x.mean(0)
        self.sx = np.where(x.std(0) < 1e-12, 1.0, x.std(0)) if self.zscore else np.ones(x.shape[1])
        self.g = self.gamma if self.gamma is not None else self.gamma_mult / x.shape[1]
        self.my, self.zt = y.mean(0), self.z(x)
        kk = self.k(self.zt, self.zt)
        kk[np.diag_indices_from(kk)] += self.alpha
        self.a = scipy.linalg.solve(kk, y - self.my, assume_a="pos")
        self.llo, self.lhi = xl.min(0), xl.max(0)
        self.lin = LinearRegressor.fit(xl, y, LinearConfig(ridge=self.ridge))
        return self

    def predict(self, x, xl=None):
        xl = np.clip(x if xl is None else xl, self.llo, self.lhi)
        fk = self.k(self.z(x), self.zt) @ self.a + self.my
        fl = xl @ self.lin.weight.double().numpy().T + self.lin.bias.double().numpy()
        return self.blend * fk + (1 - self.blend) * fl


# ------------------------------------------------------------------ variants
# A variant is method(clip, train_rows, y_train) -> predict(noisy eval landmarks (N, 68, 2)) -> b_g.

def krr(prep=None, sigma=1.0, lin_prep=None, target_smooth=False, **kw):
    """KRR on per-stream features ``prep(clip, lm_stream)`` (causal filters act per stream)."""
    prep = prep or (lambda c, lm: c.feats(lm))

    def method(c, rows, y):
        if target_smooth:  # offline 3-tap smoothing of the training targets only
            y = y.copy()
            y[1:-1] = 0.25 * y[:-2] + 0.5 * y[1:-1] + 0.25 * y[2:]
        streams = copies(c.lm[rows], sigma)
        x = np.concatenate([prep(c, s) for s in streams])
        xl = None if lin_prep is None else np.concatenate([lin_prep(c, s) for s in streams])
        reg = KRR(**kw).fit(x, np.tile(y, (len(streams), 1)), xl)
        return lambda lm: reg.predict(prep(c, lm), None if lin_prep is None else lin_prep(c, lm))
    return method


def registry(name, params, sigma=1.0):
    def method(c, rows, y):
        torch.manual_seed(0)
        lm = np.concatenate(copies(c.lm[rows], sigma))
        reg = REGISTRY[name].fit(c.feats(lm), np.tile(y, (len(lm) // len(rows), 1)), CONFIGS[name](**params)).eval()
        return lambda lme: reg.predict(c.feats(lme))
    return method


def ensemble(members):
    def method(c, rows, y):
        fs = [(w, m(c, rows, y)) for w, m in members]
        return lambda lm: sum(w * f(lm) for w, f in fs)
    return method


def ema(a, on="features"):
    def f(x):
        out, s = np.empty_like(x), x[0]
        for i in range(len(x)):
            s = a * x[i] + (1 - a) * s
            out[i] = s
        return out
    if on == "features":
        return lambda c, lm: f(c.feats(lm))
    return lambda c, lm: c.feats(f(lm.astype(np.float64)).astype(np.float32))


def one_euro(mc, beta):
    return lambda c, lm: c.feats(smooth_landmarks(lm, 30.0, mc, beta))


def velocity(lag):
    def f(c, lm):
        x = c.feats(lm)
        return np.hstack([x, x - np.vstack([np.repeat(x[:1], lag, 0), x[:-lag]])])
    return f


def shape_pcs(k=None, ard=False, n_out=5):
    """Kernel on whitened shape PCs (the model's b_s, or ``k`` PCs of the landmark features),
    optionally with GP marginal-likelihood ARD length scales (RBF + White on the leading
    whitened b_g outputs); linear part on the landmarks."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    def method(c, rows, y):
        if k is None:
            ev = np.sqrt(c.model.shape_pca.eigenvalues)
            proj = lambda lm: c.feats(lm, "bs") / ev  # noqa: E731
        else:
            f = c.feats(c.lm[rows])
            mu = f.mean(0)
            _, s, vt = np.linalg.svd(f - mu, full_matrices=False)
            proj = lambda lm: (c.feats(lm) - mu) @ vt[:k].T / (s[:k] / np.sqrt(len(f)))  # noqa: E731
        x = proj(c.lm[rows])
        kw = dict(zscore=False, gamma_mult=0.3, kernel="rbf")
        if ard:
            gp = GaussianProcessRegressor(ConstantKernel() * RBF(np.full(x.shape[1], 5.0), (1e-1, 1e4)) + WhiteKernel(0.1),
                                          normalize_y=True, random_state=0)
            gp.fit(x, y[:, :n_out] / np.sqrt(c.model.appearance_pca.eigenvalues[:n_out]))
            kw = dict(zscore=False, gamma=0.5, weights=1.0 / gp.kernel_.k1.k2.length_scale, kernel="rbf")
        return krr(lambda c_, lm: proj(lm), lin_prep=LIN, **kw)(c, rows, y)
    return method


def shrink(mode="component", nblocks=5, kernel="rbf"):
    """krr, predictions scaled toward the mean by factors fitted by blocked CV (contiguous
    blocks) inside the training rows: per b_g component, one global factor, or per
    reference-frame region (facesynth.sadm.regions.reference_regions; a per-pixel factor on the
    texture offset, which an exported model would fold into its appearance basis)."""
    from facesynth.sadm.regions import reference_regions as region_masks

    def method(c, rows, y):
        base = krr(kernel=kernel)
        p, t = [], []
        for blk in np.array_split(np.arange(len(rows)), nblocks):
            keep = np.setdiff1d(np.arange(len(rows)), blk)
            pb = base(c, rows[keep], y[keep])(c.lm[rows[blk]])
            p.append(np.clip(pb, -c.lim, c.lim) if mode == "region" else pb)
            t.append(y[blk])
        p, t = np.concatenate(p), np.concatenate(t)
        f = base(c, rows, y)
        if mode == "region":
            comp = c.model.appearance_pca.components
            nc = c.model.n_channels
            dp, dt = (p @ comp).reshape(len(p), nc, -1), (t @ comp).reshape(len(t), nc, -1)
            scale = np.zeros(dp.shape[2])
            for m in region_masks(c.model).values():
                scale[m] = np.clip((dp[:, :, m] * dt[:, :, m]).sum() / (dp[:, :, m] ** 2).sum(), 0, 1)
            mean, spix = c.model.appearance_pca.mean, np.tile(scale, nc)
            return lambda lm: mean + (np.clip(f(lm), -c.lim, c.lim) @ comp) * spix  # textures
        s = (p * t).sum(0) / np.maximum((p * p).sum(0), 1e-12)
        if mode == "global":
            s = np.full_like(s, (p * t).sum() / (p * p).sum())
        s = np.clip(s, 0, 1)
        return lambda lm: f(lm) * s
    return method


def rigid(points=None, affine=False):
    def f(c, lm):
        if points is None and not affine:
            return c.feats(lm, "landmarks_rigid")
        from facesynth.geometry import apply_affine, similarity_fit

        idx = list(points or RIGID_POINTS)
        mean = c.model.shape_pca.mean.reshape(-1, 2)
        lm = np.asarray(lm, np.float64)
        if affine:
            a = np.stack([np.linalg.lstsq(np.c_[p[idx], np.ones(len(idx))], mean[idx], rcond=None)[0].T for p in lm])
        else:
            a = similarity_fit(lm[:, idx], mean[idx])
        al = apply_affine(lm, a).reshape(len(lm), -1) - c.model.shape_pca.mean
        return al * 100.0 / (mean[:, 0].max() - mean[:, 0].min())
    return f


LIN = lambda c, lm: c.feats(lm)  # noqa: E731  (linear part on the current landmarks only)
VEL_W = np.r_[np.ones(136), np.full(136, 0.3)]  # velocity inputs at weight 0.3 after z-scoring
MLP = ("mlp", dict(hidden=[128, 128], weight_decay=1.0, dropout=0.2))
SVR = ("svr", dict(kind="epsilon", kernel="rbf", C=1.0, epsilon=0.1, gamma_mult=0.25))
VARIANTS = {
    "krr_rbf": krr(kernel="rbf"),
    "krr_matern": krr(),
    "ema_features_0.8": krr(ema(0.8), kernel="rbf"),
    "ema_features_0.6": krr(ema(0.6), kernel="rbf"),
    "ema_features_0.4": krr(ema(0.4), kernel="rbf"),
    "ema_landmarks_0.6": krr(ema(0.6, "landmarks"), kernel="rbf"),
    "one_euro_1_0.05": krr(one_euro(1.0, 0.05), kernel="rbf"),
    "one_euro_3_0.5": krr(one_euro(3.0, 0.5), kernel="rbf"),
    "velocity_1_w0.3": krr(velocity(1), kernel="rbf", gamma=0.3 / 136, weights=VEL_W, lin_prep=LIN),
    "velocity_6_w0.3": krr(velocity(6), kernel="rbf", gamma=0.3 / 136, weights=VEL_W, lin_prep=LIN),
    "velocity_2_w1": krr(velocity(2), kernel="rbf", gamma_mult=0.6, lin_prep=LIN),
    "mlp": registry(*MLP),
    "krr.5_mlp.5": ensemble([(0.5, krr(kernel="rbf")), (0.5, registry(*MLP))]),
    "krr.7_mlp.3": ensemble([(0.7, krr(kernel="rbf")), (0.3, registry(*MLP))]),
    "krr.5_svr.5": ensemble([(0.5, krr(kernel="rbf")), (0.5, registry(*SVR))]),
    "krr_mlp_svr_thirds": ensemble([(1 / 3, krr(kernel="rbf")), (1 / 3, registry(*MLP)), (1 / 3, registry(*SVR))]),
    "matern_aug0.5.6_mlp.4": ensemble([(0.6, krr(sigma=0.5)), (0.4, registry(*MLP))]),
    "matern_aug0.7_mlp.3": ensemble([(0.7, krr(sigma=0.0, alpha=0.1)), (0.3, registry(*MLP))]),
    "ard_bs": shape_pcs(None, ard=True),
    "ard_40_landmark_pcs": shape_pcs(40, ard=True),
    "whitened_bs": shape_pcs(None, ard=False),
    "rbf_unstandardised": krr(kernel="rbf", zscore=False),
    "laplacian": krr(kernel="laplacian"),
    "matern52": krr(kernel="matern52"),
    "rq_gm1": krr(kernel="rq", gamma_mult=1.0),
    "matern_two_widths": krr(gamma_mult=0.1, widths=(1.0, 10.0)),
    "matern_alpha0.25": krr(alpha=0.25),
    "matern_alpha1": krr(alpha=1.0),
    "matern_aug0.75": krr(sigma=0.75),
    "matern_aug0": krr(sigma=0.0, alpha=0.1),
    "shrink_component": shrink("component"),
    "shrink_global": shrink("global"),
    "shrink_region": shrink("region", kernel="matern32"),
    "rigid_13": krr(rigid()),
    "rigid_7": krr(rigid([36, 39, 42, 45, 27, 30, 33])),
    "rigid_13_jaw": krr(rigid(list(RIGID_POINTS) + [0, 1, 15, 16])),
    "rigid_kernel_only": krr(rigid(), lin_prep=LIN),
    "both_alignments": krr(lambda c, lm: np.hstack([c.feats(lm), rigid()(c, lm)])),
    "affine_rigid_13": krr(rigid(affine=True)),
    "affine_68": krr(rigid(list(range(68)), affine=True)),
    "linear_clipped_2px": krr(sigma=2.0, blend=0.0),
    "linear_clipped_2px_rigid": krr(rigid(), sigma=2.0, blend=0.0),
    "target_smoothing": krr(kernel="rbf", target_smooth=True),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--clips", default="lp_d6,lp_d10,lp_d3")
    ap.add_argument("--only", default=",".join(VARIANTS))
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args()
    if args.list:
        print("\n".join(VARIANTS))
        return
    torch.set_num_threads(1)
    out: dict = {}
    for name in args.clips.split(","):
        if shared_clip(name) is None:
            raise SystemExit(f"clip {name} not found under the shared data directory")
        c = Clip(name)
        for v in args.only.split(","):
            for mode in ("val", "test"):
                rows, y, ev, tex = c.split(mode)
                pred = VARIANTS[v](c, rows, y)
                s0, s2 = (c.score(pred(noisy_landmarks(c.lm[ev], s, 0)), tex) for s in (0, 2))
                out.setdefault(v, {}).setdefault(name, {})[mode] = [round(s0, 2), round(s0 - s2, 2)]
    print(json.dumps({"bench": "sadm_study", "variants": out}))


if __name__ == "__main__":
    main()
