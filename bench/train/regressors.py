"""Benchmark of the SADM regressors: fit time, predict time, held-out MSE in b_g space.

Prints ONE JSON line. Data: the shared clip (default lp_d6) when ../shared/data is
present -- face model fitted on the first 75% of the frames (temporal split), inputs
b_s (clamped) or other shape features, targets b_g of the sampled textures -- else random
data of the same size (N=1008 -> 756 train, D_in=16, D_out=150).

    python -m bench.train.regressors                       # all defaults
    python -m bench.train.regressors --search              # + default-grid search
    python -m bench.train.regressors --random --only linear,svr

Figures: ``fit_s`` (training time, all defaults), ``predict_batch_ms`` (torch forward on
all test rows at once), ``predict_frame_ms`` (batch of 1, median), ``test_mse`` (mean over
test rows and components of (b_g_hat - b_g)^2; ``mean_prediction`` is the train-mean
baseline, which corresponds to the mean-texture row), SVR support-vector counts. With
``--search``: the best grid values (validation = last 15% of the training rows) and the
held-out MSE of the refit with them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from bench.harness import emit
from facesynth.regressors import CONFIGS, DEFAULT_GRIDS, REGISTRY, search
from facesynth.regressors._common import tail_holdout


def clip_data(name: str, features: str):
    from facesynth.data import load_sequence, shared_clip, temporal_split
    from facesynth.model.face_model import FaceModel, FaceModelConfig

    path = shared_clip(name)
    if path is None:
        return None
    seq = load_sequence(path)
    train, test = temporal_split(len(seq), 0.75)
    t0 = time.perf_counter()
    model = FaceModel.fit(seq, FaceModelConfig(), rows=train, progress=False)
    if features == "bs":
        x = model.shape_params(seq.landmarks, clamp=True)
    else:
        from facesynth.sadm.synthesis import ShapeFeatures

        x = ShapeFeatures.numpy(model, seq.landmarks, features)
    y_tr = model.appearance_params(model.sample_textures(seq, train))
    y_te = model.appearance_params(model.sample_textures(seq, test))
    prep = time.perf_counter() - t0
    info = {"data": f"{name} ({features})", "prep_s": round(prep, 2)}
    return x[train], y_tr, x[test], y_te, info


def random_data(seed: int = 0):
    rng = np.random.default_rng(seed)
    n, d_in, d_out = 1008, 16, 150
    x = rng.normal(size=(n, d_in)) * np.linspace(2.0, 0.2, d_in)
    w = rng.normal(size=(d_in, d_out)) / np.sqrt(d_in)
    y = np.tanh(x) @ w * np.linspace(3.0, 0.1, d_out) + 0.1 * rng.normal(size=(n, d_out))
    k = 756
    return x[:k], y[:k], x[k:], y[k:], {"data": "random (N=1008, D_in=16, D_out=150)"}


def time_predict(reg, x: np.ndarray, repeats: int = 20) -> tuple[float, float]:
    xt = torch.from_numpy(np.asarray(x, np.float32))
    with torch.no_grad():
        reg(xt)  # warm-up
        t0 = time.perf_counter()
        for _ in range(repeats):
            reg(xt)
        batch = (time.perf_counter() - t0) / repeats
        one = []
        for i in range(min(50, len(xt))):
            t0 = time.perf_counter()
            reg(xt[i : i + 1])
            one.append(time.perf_counter() - t0)
    return 1e3 * batch, 1e3 * float(np.median(one))


def mse(a, b) -> float:
    return float(((np.asarray(a, np.float64) - b) ** 2).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", default="lp_d6")
    ap.add_argument("--features", default="bs", choices=["bs", "landmarks", "bs+landmarks", "landmarks_rigid"])
    ap.add_argument("--random", action="store_true", help="random data even when the shared clip exists")
    ap.add_argument("--only", default="linear,poly2,mlp,svr,krr", help="comma-separated regressors")
    ap.add_argument("--search", action="store_true", help="also grid-search the default grids")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=None, help="npz file to reuse the clip's (x, b_g) arrays (written if absent)")
    args = ap.parse_args(argv)

    data = None
    if args.cache and not args.random and Path(args.cache).exists():
        z = np.load(args.cache, allow_pickle=False)
        data = (z["x_tr"], z["y_tr"], z["x_te"], z["y_te"], json.loads(str(z["info"])))
    elif not args.random:
        data = clip_data(args.clip, args.features)
        if data is not None and args.cache:
            np.savez(args.cache, x_tr=data[0], y_tr=data[1], x_te=data[2], y_te=data[3], info=json.dumps(data[4]))
    x_tr, y_tr, x_te, y_te, info = data if data is not None else random_data(args.seed)
    out = {**info, "n_train": len(x_tr), "n_test": len(x_te), "d_in": x_tr.shape[1], "d_out": y_tr.shape[1],
           "torch_threads": torch.get_num_threads(), "mean_prediction_test_mse": mse(y_tr.mean(0), y_te),
           "regressors": {}}
    for name in args.only.split(","):
        t0 = time.perf_counter()
        reg = REGISTRY[name].fit(x_tr, y_tr, CONFIGS[name](), seed=args.seed)
        fit_s = time.perf_counter() - t0
        batch_ms, frame_ms = time_predict(reg, x_te)
        row = {"fit_s": round(fit_s, 3), "predict_batch_ms": round(batch_ms, 3), "predict_frame_ms": round(frame_ms, 4),
               "test_mse": mse(reg.predict(x_te), y_te), "train_mse": mse(reg.predict(x_tr), y_tr)}
        summ = reg.summary()
        row.update({k: summ[k] for k in ("n_support_union", "n_support_mean_per_output", "best_epoch") if k in summ})
        if args.search:
            fit_idx, val_idx = tail_holdout(len(x_tr), 0.15)
            t0 = time.perf_counter()
            best, table = search(name, x_tr[fit_idx], y_tr[fit_idx], x_tr[val_idx], y_tr[val_idx], seed=args.seed)
            search_s = time.perf_counter() - t0
            keys = list(DEFAULT_GRIDS[name])
            best_row = next(r for r in table if r["best"])
            reg2 = REGISTRY[name].fit(x_tr, y_tr, best, seed=args.seed)
            row["search"] = {
                "seconds": round(search_s, 1), "settings": len(table), "best": {k: best_row[k] for k in keys},
                "best_config": best_row["config"], "val_mse": {json.dumps([r[k] for k in keys]): r["val_mse"] for r in table},
                "test_mse_refit": mse(reg2.predict(x_te), y_te),
            }
        out["regressors"][name] = row
        print(f"{name}: fit {fit_s:.2f}s test_mse {row['test_mse']:.5g}", file=sys.stderr)
    emit(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
