"""Shared fixtures. Tests that need ../shared/data use ``shared_data`` / ``shared_clip_dir``
and skip cleanly when it is absent (a fresh clone); CI has it, so there they run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from facesynth.data.shared import shared_clip, shared_data_dir, shared_mesh_dir
from facesynth.eri.config import EriConfig
from facesynth.eri.model import EriModel
from tests._eri import CFG, _sequence


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = shared_data_dir()
    if root is None:
        pytest.skip("../shared/data is absent")
    return root


@pytest.fixture(scope="session")
def shared_clip_dir():
    """Factory: ``shared_clip_dir('lp_d6')`` -> Path, or skip."""

    def get(name: str) -> Path:
        p = shared_clip(name)
        if p is None:
            pytest.skip(f"../shared/data/faces/{name} is absent")
        return p

    return get


@pytest.fixture(scope="session")
def shared_mesh() -> Path:
    p = shared_mesh_dir()
    if p is None:
        pytest.skip("../shared/data/mesh is absent")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="module")
def seq():
    """The small synthetic ERI subject (tests/_eri.py): 16 frames, mouth opening darkens the chin."""
    return _sequence()


@pytest.fixture(scope="module")
def model(seq):
    """An ERI model fitted on the first 12 frames of ``seq`` (tests/_eri.py's CFG)."""
    return EriModel.fit(seq, np.arange(12), EriConfig(**CFG))
