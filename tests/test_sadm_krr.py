"""The ``krr`` regressor (Matern 3/2 or RBF kernel ridge blended with linear ridge): scikit-learn
cross-checks, the blend end points, save/load, ONNX parity, config errors, and the
synthetic subject's held-out frames through fit_sadm."""

import json

import numpy as np
import pytest
import torch

from facesynth.errors import FacesynthError
from facesynth.regressors import DEFAULT_GRIDS, REGISTRY, KRRConfig, KRRRegressor, LinearRegressor, search


def _data(n=160, d=6, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, d)) * np.linspace(0.5, 4.0, d) + 2.0
    y = np.c_[np.sin(x[:, 0]) + 0.3 * x[:, 1] ** 2, x[:, 2] * x[:, 3], x[:, 4] - x[:, 5]] * [5.0, 1.0, 0.1] + [10.0, -3.0, 0.0]
    return x, y


def test_krr_equals_sklearn_kernel_ridge_plus_ridge():
    from sklearn.kernel_ridge import KernelRidge
    from sklearn.linear_model import Ridge
    from sklearn.preprocessing import StandardScaler

    x, y = _data()
    xt, _ = _data(40, seed=1)
    cfg = KRRConfig(alpha=0.3, gamma_mult=0.5, ridge=2.0, blend=0.6, clip_inputs=False, kernel="rbf")
    reg = KRRRegressor.fit(x, y, cfg)
    sc = StandardScaler().fit(x)
    krr = KernelRidge(alpha=0.3, kernel="rbf", gamma=0.5 / x.shape[1]).fit(sc.transform(x), y - y.mean(0))
    lin = Ridge(alpha=2.0).fit(x, y)
    want = 0.6 * (krr.predict(sc.transform(xt)) + y.mean(0)) + 0.4 * lin.predict(xt)
    np.testing.assert_allclose(reg.predict(xt), want, rtol=1e-4, atol=1e-4 * np.abs(want).max())


def test_matern32_equals_sklearn_kernel_ridge_with_matern_kernel():
    from sklearn.gaussian_process.kernels import Matern
    from sklearn.kernel_ridge import KernelRidge
    from sklearn.preprocessing import StandardScaler

    x, y = _data()
    xt, _ = _data(40, seed=1)
    reg = KRRRegressor.fit(x, y, {"alpha": 0.2, "gamma_mult": 0.7, "blend": 1.0, "clip_inputs": False})
    assert reg.config.kernel == "matern32"  # the default
    sc = StandardScaler().fit(x)
    kern = Matern(length_scale=1.0 / np.sqrt(0.7 / x.shape[1]), nu=1.5)
    krr = KernelRidge(alpha=0.2, kernel=kern).fit(sc.transform(x), y - y.mean(0))
    want = krr.predict(sc.transform(xt)) + y.mean(0)
    np.testing.assert_allclose(reg.predict(xt), want, rtol=1e-4, atol=1e-4 * np.abs(want).max())
    # exactly at a centre (distance 0, where float32 cancellation is largest) it stays finite and equal
    np.testing.assert_allclose(reg.predict(x[:5]), krr.predict(sc.transform(x[:5])) + y.mean(0),
                               rtol=1e-4, atol=1e-4 * np.abs(want).max())


def test_global_scale_equals_sklearn_on_inputs_divided_by_their_rms_std():
    from sklearn.gaussian_process.kernels import Matern
    from sklearn.kernel_ridge import KernelRidge

    x, y = _data()
    xt, _ = _data(40, seed=1)
    reg = KRRRegressor.fit(x, y, {"alpha": 0.2, "gamma_mult": 0.7, "blend": 1.0, "clip_inputs": False, "scale": "global"})
    mx, s = x.mean(0), np.sqrt(np.mean(x.std(0) ** 2))  # one scale: the inputs keep their relative spreads
    kern = Matern(length_scale=1.0 / np.sqrt(0.7 / x.shape[1]), nu=1.5)
    krr = KernelRidge(alpha=0.2, kernel=kern).fit((x - mx) / s, y - y.mean(0))
    want = krr.predict((xt - mx) / s) + y.mean(0)
    np.testing.assert_allclose(reg.predict(xt), want, rtol=1e-4, atol=1e-4 * np.abs(want).max())
    assert reg.config_dict()["scale"] == "global"


def test_blend_end_points():
    from sklearn.kernel_ridge import KernelRidge

    x, y = _data()
    lin = LinearRegressor.fit(x, y, {"ridge": 1.5})
    zero = KRRRegressor.fit(x, y, {"blend": 0.0, "ridge": 1.5})  # inside the training box: no clipping
    np.testing.assert_allclose(zero.predict(x), lin.predict(x), rtol=1e-5, atol=1e-4)
    one = KRRRegressor.fit(x, y, {"blend": 1.0, "alpha": 0.1, "gamma_mult": 1.0, "kernel": "rbf"})
    z = (x - x.mean(0)) / x.std(0)
    ref = KernelRidge(alpha=0.1, kernel="rbf", gamma=1.0 / x.shape[1]).fit(z, y).predict(z)
    # KernelRidge without centring differs; with centred targets it is exact:
    ref_c = KernelRidge(alpha=0.1, kernel="rbf", gamma=1.0 / x.shape[1]).fit(z, y - y.mean(0)).predict(z) + y.mean(0)
    np.testing.assert_allclose(one.predict(x), ref_c, rtol=1e-4, atol=1e-3)
    assert np.abs(ref - ref_c).max() > 1e-3  # the centring matters (so the check above is specific)


def test_clip_inputs_maps_outside_shapes_to_the_training_box():
    x, y = _data()
    reg = KRRRegressor.fit(x, y)  # clip_inputs=True (default)
    free = KRRRegressor.fit(x, y, {"clip_inputs": False})
    np.testing.assert_allclose(reg.predict(x), free.predict(x), rtol=1e-6, atol=1e-5)  # inside: identical
    far = x[:5] + 100.0 * np.sign(x[:5] - x.mean(0))  # far outside the box in every coordinate
    box = np.where(far > x.max(0), x.max(0), np.where(far < x.min(0), x.min(0), far))
    np.testing.assert_allclose(reg.predict(far), free.predict(box), rtol=1e-5, atol=1e-4)
    assert np.abs(free.predict(far)).max() > 10 * np.abs(reg.predict(far)).max()  # the linear part extrapolates


def test_kernel_part_interpolates_with_small_alpha():
    x, y = _data(60)
    reg = KRRRegressor.fit(x, y, {"blend": 1.0, "alpha": 1e-6, "gamma_mult": 2.0})
    np.testing.assert_allclose(reg.predict(x), y, atol=1e-2 * np.abs(y).max())


@pytest.mark.parametrize("kernel", ["matern32", "rbf"])
def test_round_trip_and_onnx_parity(tmp_path, kernel):
    import onnxruntime as ort

    x, y = _data()
    reg = KRRRegressor.fit(x, y, {"kernel": kernel}).eval()
    cfg = json.loads(json.dumps(reg.config_dict()))
    again = REGISTRY["krr"].from_state(cfg, {k: v.clone() for k, v in reg.state_dict().items()})
    np.testing.assert_array_equal(again.predict(x), reg.predict(x))
    assert again.summary() == reg.summary() and again.summary()["n_centres"] == len(x)
    path = tmp_path / "krr.onnx"
    torch.onnx.export(reg, (torch.zeros(2, x.shape[1]),), str(path), dynamo=False, opset_version=18,
                      input_names=["x"], output_names=["y"], dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}})
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    xs = x[:37].astype(np.float32)
    (got,) = sess.run(None, {"x": xs})
    np.testing.assert_allclose(got, reg.predict(xs), rtol=1e-5, atol=1e-5 * np.abs(y).max())


def test_factored_centres_give_float64_distances_on_low_rank_inputs():
    """Inputs on a 5-dimensional plane in 40 dimensions (as a face's aligned landmarks lie on a
    few dozen of their 956): the centres are stored as 5 coordinates, and the factored squared
    distances equal float64's to float32 rounding, for inputs off the plane too."""
    from facesynth.regressors.krr import factor_centres

    rng = np.random.default_rng(3)
    c = rng.normal(size=(300, 5)) @ rng.normal(size=(5, 40)) + rng.normal(size=40)
    f = factor_centres(c)
    assert f["proj"].shape == (40, 5) and f["coords"].shape == (300, 5)
    np.testing.assert_allclose(f["proj"].T @ f["proj"], np.eye(5), atol=1e-12)
    s = rng.normal(size=(20, 40)) * 0.5 + c[:20]
    want = ((s[:, None] - c[None]) ** 2).sum(-1)
    t = {k: torch.from_numpy(v).float() for k, v in f.items()}
    sc = torch.from_numpy(s).float() - t["centre_mean"]
    got = (sc * sc).sum(1, keepdim=True) + t["centres_sq"] - 2.0 * (sc @ t["proj"]) @ t["coords"].T
    np.testing.assert_allclose(got.double().numpy(), want, rtol=2e-6, atol=2e-6 * want.max())


def test_a_state_with_unfactored_centres_loads_factored():
    x, y = _data()
    reg = KRRRegressor.fit(x, y, KRRConfig(blend=1.0))
    t = {k: v.clone() for k, v in reg.state_dict().items()}
    c = (t.pop("coords").double() @ t.pop("proj").double().T + t.pop("centre_mean").double()).float()
    t.pop("centres_sq")
    again = KRRRegressor.from_state(reg.config_dict(), {**t, "centres": c, "centres_sq": (c.double() ** 2).sum(1).float()})
    np.testing.assert_allclose(again.predict(x[:30]), reg.predict(x[:30]), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("bad", [{"alpha": 0.0}, {"gamma_mult": -1.0}, {"blend": 1.5}, {"ridge": -1.0}, {"alhpa": 1.0},
                                 {"kernel": "laplacian"}, {"scale": "minmax"}])
def test_bad_config_is_a_clear_error(bad):
    x, y = _data(20)
    with pytest.raises(FacesynthError, match="regressor krr"):
        KRRRegressor.fit(x, y, bad)


def test_search_grid_runs_on_validation_slice():
    x, y = _data(120)
    grid = {k: v[:2] for k, v in DEFAULT_GRIDS["krr"].items()}
    best, table = search("krr", x[:90], y[:90], x[90:], y[90:], grid)
    assert isinstance(best, KRRConfig) and len(table) == 8 and sum(r["best"] for r in table) == 1


def test_synthetic_subject_held_out_beats_mean_texture():
    """Through fit_sadm/evaluate_sadm on the synthetic subject: well above the mean texture."""
    from facesynth.data import temporal_split
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.eval.sadm_eval import EvalConfig, evaluate_sadm
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.sadm.fit import SADMConfig, fit_sadm, load_sadm, save_sadm

    seq = make_synthetic_sequence(120, 192, seed=0)
    tr, te = temporal_split(len(seq), 0.75)
    model, tex_tr = FaceModel.fit_with_textures(seq, FaceModelConfig(reference_width=64), rows=tr, progress=False)
    sadm = fit_sadm(model, seq, tr, tex_tr, "krr", {}, SADMConfig(augment_copies=1))
    m, _ = evaluate_sadm(sadm, seq, tr, te, EvalConfig(noise=[0, 2], frame_level=False, train_level=False))
    ref = m["psnr_ref"]
    assert ref["sadm"]["0"] > ref["mean_texture"]["0"] + 1.0  # measured +1.8 dB (linear ridge: +1.9)
    assert ref["sadm"]["2"] > ref["mean_texture"]["2"] + 1.0
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        save_sadm(sadm, d)
        back = load_sadm(d)
        lm = torch.from_numpy(seq.landmarks[te[:3]])
        with torch.no_grad():
            torch.testing.assert_close(back.synthesizer()(lm)[0], sadm.synthesizer()(lm)[0])


def test_hydra_regressor_krr_composes():
    from hydra import compose, initialize_config_dir

    from facesynth.runs.config import CONF_DIR, register_configs, regressor_params

    register_configs()
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        cfg = compose(config_name="config", overrides=["regressor=krr", "regressor.blend=0.25"])
        default = compose(config_name="config", overrides=[])
        linear = compose(config_name="config", overrides=["regressor=linear"])
        again = compose(config_name="config", overrides=["regressor=krr", "sadm.augment_sigma=2"])
    name, params = regressor_params(cfg.regressor)
    assert name == "krr" and params["blend"] == 0.25 and params["alpha"] == 0.5 and params["clip_inputs"] is True
    assert params["kernel"] == "matern32"
    # krr is the default and brings its own augmentation (sigma 1 px); other regressors keep 2 px
    assert regressor_params(default.regressor)[0] == "krr" and default.sadm.augment_sigma == 1.0
    assert linear.sadm.augment_sigma == 2.0 and again.sadm.augment_sigma == 2.0



def test_ceiling_study_on_real_clip(shared_clip_dir, tmp_path):
    """facesynth.sadm.ceiling on lp_d3: the regressor lies between the mean texture and the
    PCA oracle, and covering half of the test distribution helps (the segment shift)."""
    from facesynth.sadm.ceiling import study

    res = study(str(shared_clip_dir("lp_d3")), "krr")
    assert res["mean_texture"] < res["train_to_B"] < res["oracle"]
    assert res["train_plus_A_to_B"] > res["train_to_B"] + 1.0  # measured +2.6 dB on lp_d3
    assert res["test_b_frames"] > 0
    reg = res["regions"]["train_to_B"]
    assert sum(reg[k]["pixel_share"] for k in ("eyes", "mouth_interior", "lips", "brows", "rest")) == pytest.approx(1.0)
    assert sum(reg[k]["error_share"] for k in ("eyes", "mouth_interior", "lips", "brows", "rest")) == pytest.approx(1.0)
    assert reg["eyes"]["psnr"] < reg["rest"]["psnr"]  # the eyes are the worst-predicted region
    assert reg["eyes_interior_at_oracle"] > res["train_to_B"]


def test_region_breakdown_closed_form():
    """Regions are disjoint and cover the mask; shares and PSNRs match a hand computation."""
    from facesynth.data.synthetic import make_synthetic_sequence
    from facesynth.model import FaceModel, FaceModelConfig
    from facesynth.sadm.ceiling import region_breakdown
    from facesynth.sadm.regions import reference_regions as region_masks

    seq = make_synthetic_sequence(24, 128, seed=0)
    model = FaceModel.fit(seq, FaceModelConfig(reference_width=64), progress=False)
    masks = region_masks(model)
    stack = np.stack(list(masks.values()))
    assert stack.shape == (5, model.n_pixels) and (stack.sum(0) == 1).all()  # a partition of the mask
    assert all(m.any() for m in masks.values())
    c, n = model.n_channels, 3
    true = np.random.default_rng(0).uniform(0.2, 0.8, (n, c * model.n_pixels))
    eyes = np.tile(masks["eyes"], c)
    pred = true + np.where(eyes, 0.1, 0.01)  # 10x the error amplitude in the eyes
    oracle = true + 0.01
    out = region_breakdown(model, pred, true, oracle)
    ne, m = masks["eyes"].sum(), model.n_pixels
    assert out["eyes"]["error_share"] == pytest.approx(100 * ne / (100 * ne + m - ne), rel=1e-6)
    assert out["eyes"]["psnr"] == pytest.approx(20 * np.log10(255 / 25.5), abs=1e-6)
    assert out["rest"]["psnr"] == pytest.approx(40.0, abs=1e-6) and out["rest"]["oracle_psnr"] == pytest.approx(40.0, abs=1e-6)
    # the interior's error is already at the oracle's level; the eyes' swap leaves 0.01 everywhere
    assert out["eyes_interior_at_oracle"] == pytest.approx(40.0, abs=1e-6)


def test_ceiling_cli_reports_missing_clip(tmp_path):
    from facesynth.errors import FacesynthError
    from facesynth.sadm.ceiling import main

    with pytest.raises(FacesynthError):
        main(["--clip", str(tmp_path / "nope")])
