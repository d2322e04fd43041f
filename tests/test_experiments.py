"""Every named study (``facesynth/conf/experiment/NAME.yaml``, ``facesynth train experiment=NAME``)
composes with the training schema (Hydra, no training), changes the default config, and is
listed in docs/sadm.md's table of studies."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from facesynth.runs.config import CONF_DIR, register_configs

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
DOCS = Path(__file__).resolve().parents[1] / "docs" / "sadm.md"


def _compose(overrides: list[str], hydra_node: bool = False):
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides, return_hydra_config=hydra_node)


def _changes(a, b, prefix: str = "") -> dict:
    """Keys whose values differ between two nested dicts: {dotted key: (a's, b's)}."""
    out = {}
    for k in sorted(set(a) | set(b)):
        x, y = a.get(k), b.get(k)
        if isinstance(x, dict) and isinstance(y, dict):
            out.update(_changes(x, y, f"{prefix}{k}."))
        elif x != y:
            out[f"{prefix}{k}"] = (x, y)
    return out


def test_there_are_experiments():
    assert "rigid_features" in EXPERIMENTS and len(EXPERIMENTS) >= 5


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_composes_and_differs_from_the_default(name):
    default = _compose([], hydra_node=True)
    cfg = _compose([f"experiment={name}"], hydra_node=True)
    assert cfg.hydra.runtime.choices.experiment == name
    changes = _changes(OmegaConf.to_container(default, resolve=False), OmegaConf.to_container(cfg, resolve=False))
    changes = {k: v for k, v in changes.items() if not k.startswith(("hydra.runtime", "hydra.overrides", "hydra.job."))}
    assert changes, f"experiment={name} changes nothing"
    job = _compose([f"experiment={name}"])  # the training config as run_training reads it, resolved
    OmegaConf.to_container(job, resolve=True)


def test_experiment_values_reach_the_config():
    cfg = _compose(["experiment=rigid_features"])
    assert cfg.sadm.features == "landmarks_rigid" and cfg.eval.frame_level is False
    cfg = _compose(["experiment=krr_rbf"])
    assert (cfg.regressor.name, cfg.regressor.kernel, cfg.sadm.augment_sigma) == ("krr", "rbf", 2.0)
    assert _compose(["experiment=rigid_features", "sadm.features=landmarks"]).sadm.features == "landmarks"  # CLI wins
    sweep = _compose(["experiment=compare_regressors"], hydra_node=True)
    assert sweep.hydra.sweeper.params.regressor == "linear,poly2,mlp,svr,krr"


def test_every_experiment_is_in_the_docs_table():
    text = DOCS.read_text()
    for name in EXPERIMENTS:
        assert f"`{name}`" in text, f"docs/sadm.md does not list experiment={name}"
