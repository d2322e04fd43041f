"""Regressors against independent references: closed forms, scikit-learn, onnxruntime."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import torch

from facesynth.errors import FacesynthError
from facesynth.regressors import (
    CONFIGS,
    DEFAULT_GRIDS,
    REGISTRY,
    LinearRegressor,
    MLPConfig,
    MLPRegressor,
    Poly2Config,
    Poly2Regressor,
    SVRConfig,
    SVRRegressor,
    search,
)


def smooth_problem(n=300, d_in=4, d_out=6, noise=0.05, seed=0):
    """A smooth nonlinear map with outputs of different scales and offsets."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, d_in)) * rng.uniform(0.5, 3.0, d_in) + rng.normal(size=d_in)
    z = (x - x.mean(0)) / x.std(0)
    base = np.stack([np.sin(z[:, 0]) + 0.5 * z[:, 1] ** 2, np.cos(z[:, 1]) * z[:, 0], np.tanh(z[:, 2] + z[:, -1])], 1)
    mix = rng.normal(size=(3, d_out))
    y = base @ mix * rng.uniform(0.1, 5.0, d_out) + rng.normal(size=d_out) * 3
    return x, y + noise * rng.normal(size=y.shape) * y.std(0)


# Small, fast configurations used by the generic (round trip / ONNX) tests.
FAST = {
    "linear": {"ridge": 0.1},
    "poly2": {"ridge": 1.0},
    "mlp": {"hidden": [32, 32], "max_epochs": 20, "patience": 5},
    "svr": {"C": 1.0},
    "svr_linear": {"kernel": "linear", "kind": "nu"},
}


def fitted(key):
    name = "svr" if key.startswith("svr") else key
    x, y = smooth_problem(n=150)
    return REGISTRY[name].fit(x, y, FAST[key], seed=0), x


# ------------------------------------------------------------------ linear
def test_linear_equals_closed_form_eq5():
    x, y = smooth_problem(n=120, d_in=5, d_out=7)
    reg = LinearRegressor.fit(x, y, {"ridge": 0.0})  # the paper's plain least squares
    # A = G S^T (S S^T)^-1 on centred data (columns are frames), bias = mean_G - A mean_S
    s = (x - x.mean(0)).T
    g = (y - y.mean(0)).T
    a = g @ s.T @ np.linalg.inv(s @ s.T)
    b = y.mean(0) - a @ x.mean(0)
    np.testing.assert_allclose(reg.weight.numpy(), a, rtol=1e-4, atol=1e-5 * np.abs(a).max())
    np.testing.assert_allclose(reg.predict(x), x @ a.T + b, atol=1e-4 * y.std())


def test_linear_ridge_equals_sklearn_ridge():
    from sklearn.linear_model import Ridge

    x, y = smooth_problem(n=80, d_in=6, d_out=5)
    reg = LinearRegressor.fit(x, y, {"ridge": 25.0})
    ref = Ridge(alpha=25.0).fit(x, y)
    np.testing.assert_allclose(reg.predict(x), ref.predict(x), atol=1e-4 * y.std())


# ------------------------------------------------------------------ poly2
@pytest.mark.parametrize("n,d_in,ridge", [(200, 4, 0.5), (60, 12, 3.0)])  # primal (F < N) and dual (F > N)
def test_poly2_equals_sklearn_pipeline(n, d_in, ridge):
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    x, y = smooth_problem(n=n, d_in=d_in)
    reg = Poly2Regressor.fit(x, y, Poly2Config(ridge=ridge, relative_ridge=False, input_components=None))
    ref = make_pipeline(StandardScaler(), PolynomialFeatures(2, include_bias=False), Ridge(alpha=ridge)).fit(x, y)
    x_new = smooth_problem(n=50, d_in=d_in, seed=1)[0]
    np.testing.assert_allclose(reg.predict(x_new), ref.predict(x_new), atol=1e-4 * y.std(0).max())


def test_poly2_on_whitened_principal_components_equals_sklearn_pipeline():
    from sklearn.decomposition import PCA
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    x, y = smooth_problem(n=120, d_in=10)
    reg = Poly2Regressor.fit(x, y, Poly2Config(ridge=0.7, relative_ridge=False, input_components=4))
    ref = make_pipeline(StandardScaler(), PCA(4, whiten=True), PolynomialFeatures(2, include_bias=False),
                        Ridge(alpha=0.7)).fit(x, y)
    x_new = smooth_problem(n=40, d_in=10, seed=1)[0]
    np.testing.assert_allclose(reg.predict(x_new), ref.predict(x_new), atol=1e-4 * y.std(0).max())
    back = Poly2Regressor.from_state(reg.config_dict(), dict(reg.state_dict()))
    np.testing.assert_array_equal(back.predict(x_new), reg.predict(x_new))


def test_poly2_without_standardise_or_linear_terms():
    from sklearn.linear_model import Ridge
    from sklearn.preprocessing import PolynomialFeatures

    x, y = smooth_problem(n=150, d_in=3)
    reg = Poly2Regressor.fit(x, y, {"ridge": 0.2, "relative_ridge": False, "standardise": False, "include_linear": False,
                                    "input_components": None})
    quad = PolynomialFeatures(2, include_bias=False).fit_transform(x)[:, 3:]  # drop the linear block
    ref = Ridge(alpha=0.2).fit(quad, y)
    np.testing.assert_allclose(reg.predict(x), ref.predict(quad), atol=1e-4 * y.std(0).max())


def test_poly2_relative_ridge_scales_by_mean_feature_energy():
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    x, y = smooth_problem(n=120, d_in=4)
    rel = Poly2Regressor.fit(x, y, {"ridge": 0.5, "input_components": None})  # relative_ridge=True is the default
    phi = PolynomialFeatures(2, include_bias=False).fit_transform(StandardScaler().fit_transform(x))
    unit = ((phi - phi.mean(0)) ** 2).sum() / len(x)  # trace(Phi_c^T Phi_c) / N
    assert rel.lam == pytest.approx(0.5 * unit)
    ab = Poly2Regressor.fit(x, y, {"ridge": 0.5 * unit, "relative_ridge": False, "input_components": None})
    np.testing.assert_allclose(rel.predict(x), ab.predict(x), atol=1e-5 * y.std())


# ------------------------------------------------------------------ SVR
@pytest.mark.parametrize("kind", ["epsilon", "nu"])
@pytest.mark.parametrize("kernel", ["rbf", "linear"])
def test_svr_torch_equals_sklearn_predict(kind, kernel):
    from sklearn.preprocessing import StandardScaler

    x, y = smooth_problem(n=200, d_in=5, d_out=4)
    cfg = SVRConfig(kind=kind, kernel=kernel, C=3.0, epsilon=0.1, nu=0.4, gamma_mult=0.5)
    reg = SVRRegressor.fit(x, y, cfg)
    # scikit-learn's own predict of the fitted per-output models, on inputs standardised
    # here by StandardScaler and targets un-standardised by the training mean/std
    sx = StandardScaler().fit(x)
    x_new = smooth_problem(n=60, d_in=5, d_out=4, seed=3)[0]
    assert len(reg.estimators_) == y.shape[1]
    ref = np.stack(
        [est.predict(sx.transform(x_new)) * y[:, j].std() + y[:, j].mean() for j, est in enumerate(reg.estimators_)], 1
    )
    got = reg.predict(x_new)
    assert np.abs(got - ref).max() <= 1e-4 * y.std(0).max()
    n_sv = [len(est.support_) for est in reg.estimators_]
    summ = reg.summary()
    assert summ["n_support_mean_per_output"] == pytest.approx(np.mean(n_sv))
    assert max(n_sv) <= summ["n_support_union"] <= len(x)


def test_svr_matches_independently_fitted_sklearn():
    """Fits of scikit-learn's SVR/NuSVR made here (tight tolerance on both sides) agree."""
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import NuSVR

    x, y = smooth_problem(n=150, d_in=5, d_out=3)
    reg = SVRRegressor.fit(x, y, SVRConfig(kind="nu", C=3.0, nu=0.4, tol=1e-8, gamma_mult=1.0))
    z = StandardScaler().fit_transform(x)
    for j in range(y.shape[1]):
        m, s = y[:, j].mean(), y[:, j].std()
        est = NuSVR(C=3.0, nu=0.4, tol=1e-8).fit(z, (y[:, j] - m) / s)
        np.testing.assert_allclose(reg.predict(x)[:, j], est.predict(z) * s + m, atol=1e-4 * s)


def test_svr_union_of_support_vectors_is_one_kernel_matrix():
    reg, x = fitted("svr")
    s = reg.summary()["n_support_union"]
    assert reg.sv.shape == (s, x.shape[1]) and reg.coef.shape == (6, s)
    # each output uses exactly its own support vectors (the rest of its row is zero)
    assert ((reg.coef != 0).sum(1).numpy() == np.array(reg.info["n_support_per_output"])).all()


# ------------------------------------------------------------------ MLP
def test_mlp_is_deterministic_and_fits_a_smooth_function():
    x, y = smooth_problem(n=700, d_in=4, d_out=6, noise=0.02)
    tr, te = slice(0, 550), slice(550, None)
    cfg = MLPConfig(hidden=[64, 64], max_epochs=150, patience=20, weight_decay=1e-3, lr=3e-3)
    a = MLPRegressor.fit(x[tr], y[tr], cfg, seed=7)
    b = MLPRegressor.fit(x[tr], y[tr], cfg, seed=7)
    c = MLPRegressor.fit(x[tr], y[tr], cfg, seed=8)
    pa = a.predict(x[te])
    np.testing.assert_array_equal(pa, b.predict(x[te]))
    assert not np.array_equal(pa, c.predict(x[te]))
    r2 = 1 - ((pa - y[te]) ** 2).sum(0) / ((y[te] - y[te].mean(0)) ** 2).sum(0)
    assert r2.min() > 0.9, r2
    assert 1 <= a.info["best_epoch"] <= a.info["epochs_run"] <= 150


def test_mlp_holds_out_the_last_rows_when_no_validation_slice(monkeypatch):
    x, y = smooth_problem(n=100)
    seen = {}
    cfg = MLPConfig(hidden=[8], max_epochs=2, patience=1, val_fraction=0.2)
    import facesynth.regressors.mlp as mlp_mod

    real = mlp_mod.standardiser

    def spy(a, *args, **kw):
        seen.setdefault("x", a)
        return real(a, *args, **kw)

    monkeypatch.setattr(mlp_mod, "standardiser", spy)
    MLPRegressor.fit(x, y, cfg)
    np.testing.assert_array_equal(seen["x"], x[:80])  # trained on the leading 80%


# ------------------------------------------------------------------ generic
@pytest.mark.parametrize("key", list(FAST))
def test_round_trip_config_and_state(key):
    reg, x = fitted(key)
    cfg = json.loads(json.dumps(reg.config_dict()))
    buf = io.BytesIO()
    torch.save(reg.state_dict(), buf)
    buf.seek(0)
    tensors = torch.load(buf)
    again = type(reg).from_state(cfg, tensors)
    np.testing.assert_array_equal(again.predict(x), reg.predict(x))
    assert again.summary() == reg.summary()


@pytest.mark.parametrize("key", list(FAST))
def test_onnx_export_matches_torch(key, tmp_path):
    import onnxruntime as ort

    reg, x = fitted(key)
    path = tmp_path / f"{key}.onnx"
    torch.onnx.export(
        reg.eval(), (torch.zeros(2, x.shape[1]),), str(path), dynamo=False, opset_version=18,
        input_names=["x"], output_names=["y"], dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}},
    )
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    xs = x[:37].astype(np.float32)
    (got,) = sess.run(None, {"x": xs})
    want = reg.predict(xs)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * max(1.0, np.abs(want).max()))


def test_configs_are_hydra_structured_configs():
    from omegaconf import OmegaConf

    for name, cls in CONFIGS.items():
        node = OmegaConf.structured(cls)
        reg_cls = REGISTRY[name]
        assert reg_cls.name == name
        assert set(OmegaConf.to_container(node)) == set(cls.__dataclass_fields__)
    # a DictConfig is accepted as a config
    x, y = smooth_problem(n=60)
    reg = Poly2Regressor.fit(x, y, OmegaConf.structured(Poly2Config(ridge=2.0)))
    assert reg.config_dict()["ridge"] == 2.0


@pytest.mark.parametrize(
    "name,config,x_rows,match",
    [
        ("poly2", {"rige": 1.0}, 50, "unknown config key"),
        ("svr", {"kernel": "poly"}, 50, "kernel must be"),
        ("svr", {"gamma": "wide"}, 50, "gamma must be"),
        ("mlp", {"activation": "swish2", "max_epochs": 1}, 50, "activation must be"),
        ("svr", {}, 49, "rows"),
    ],
)
def test_bad_input_raises_facesynth_error(name, config, x_rows, match):
    x, y = smooth_problem(n=50)
    with pytest.raises(FacesynthError, match=match):
        REGISTRY[name].fit(x[:x_rows], y, config)


def test_nan_inputs_rejected():
    x, y = smooth_problem(n=50)
    x[3, 1] = np.nan
    with pytest.raises(FacesynthError, match="NaN"):
        Poly2Regressor.fit(x, y)


# ------------------------------------------------------------------ search
def test_default_grids_reach_far():
    assert min(DEFAULT_GRIDS["svr"]["C"]) <= 0.01 and max(DEFAULT_GRIDS["svr"]["C"]) >= 10
    assert min(DEFAULT_GRIDS["svr"]["gamma_mult"]) <= 0.0625 and max(DEFAULT_GRIDS["svr"]["gamma_mult"]) >= 2
    for name in ("linear", "poly2"):
        rel = DEFAULT_GRIDS[name]["ridge_rel"]
        assert min(rel) <= 1e-3 and max(rel) >= 1e3
    assert set(DEFAULT_GRIDS) == set(REGISTRY)


def test_search_picks_known_best_ridge():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(120, 8))
    grid = {"ridge_rel": [1e-4, 1e-1, 1e3]}
    # pure noise target: the best prediction is the mean -> the strongest ridge
    noise = rng.normal(size=(120, 3))
    best, table = search("linear", x[:80], noise[:80], x[80:], noise[80:], grid)
    assert [r["best"] for r in table] == [False, False, True]
    # noise-free linear target: the weakest ridge
    y = x @ rng.normal(size=(8, 3))
    best, table = search("linear", x[:80], y[:80], x[80:], y[80:], grid)
    assert table[0]["best"] and best.ridge == pytest.approx(1e-4 * x[:80].var(0).sum())


def test_search_scores_equal_sklearn_and_weights():
    from sklearn.linear_model import Ridge

    x, y = smooth_problem(n=200, d_in=5, d_out=4, noise=0.5)
    w = np.array([1.0, 0.0, 0.0, 0.0])
    best, table = search("linear", x[:150], y[:150], x[150:], y[150:], {"ridge_rel": [1e-2, 1.0, 30.0]}, weights=w)
    unit = x[:150].var(0).sum()
    for row in table:
        ref = Ridge(alpha=row["ridge_rel"] * unit).fit(x[:150], y[:150]).predict(x[150:])
        assert row["val_mse"] == pytest.approx(((ref[:, 0] - y[150:, 0]) ** 2).mean() / 4, rel=1e-4)
    assert sum(r["best"] for r in table) == 1
    assert best.ridge == pytest.approx(min(table, key=lambda r: r["val_mse"])["config"]["ridge"])


def test_search_svr_prefers_rbf_on_a_nonlinear_problem():
    x, y = smooth_problem(n=240, d_in=3, d_out=2, noise=0.02)
    y = np.stack([np.sin(2 * x[:, 0] / x[:, 0].std()), (x[:, 1] / x[:, 1].std()) ** 2], 1)
    best, table = search(
        "svr", x[:180], y[:180], x[180:], y[180:], {"kernel": ["linear", "rbf"], "gamma_mult": [1.0]},
        base_config={"C": 3.0},
    )
    assert best.kernel == "rbf" and len(table) == 2
    reg = SVRRegressor.fit(x[:180], y[:180], best)
    assert reg.summary()["gamma"] == pytest.approx(1.0 / 3, rel=1e-6)  # 'scale' on standardised inputs = 1 / D


def test_search_rejects_bad_grid():
    x, y = smooth_problem(n=50)
    with pytest.raises(FacesynthError, match="unknown grid key"):
        search("poly2", x[:40], y[:40], x[40:], y[40:], {"gamma_mult": [1.0]})
    with pytest.raises(FacesynthError, match="unknown regressor"):
        search("forest", x[:40], y[:40], x[40:], y[40:], {})


def test_search_poly2_relative_ridge_is_passed_through():
    x, y = smooth_problem(n=120, d_in=3)
    best, table = search("poly2", x[:90], y[:90], x[90:], y[90:], {"ridge_rel": [0.1, 10.0]})
    assert [r["config"]["ridge"] for r in table] == [0.1, 10.0]
    assert all(r["config"]["relative_ridge"] for r in table)
    # the same settings with absolute ridge give the same scores
    _, table_abs = search("poly2", x[:90], y[:90], x[90:], y[90:], {"ridge_rel": [0.1, 10.0]}, {"relative_ridge": False})
    for a, b in zip(table, table_abs, strict=True):
        assert a["val_mse"] == pytest.approx(b["val_mse"], rel=1e-5)
