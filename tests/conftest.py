"""Shared fixtures. Real assets are the bundled package data (meshsplat/assets)."""

from __future__ import annotations

import os

import pytest
import torch

from _train_kit import tiny_dataset  # noqa: F401  (the tiny capture fixture, for every test module)
from meshsplat.paths import assets_dir
from meshsplat.synth.standin_models import write_standin_models

os.environ.setdefault("HYPOTHESIS_PROFILE", "ci")
try:
    from hypothesis import HealthCheck, settings

    # under CI (CI=true) the examples are derandomized so a run is reproducible; locally they vary
    settings.register_profile(
        "ci",
        deadline=None,
        max_examples=40,
        derandomize=bool(os.environ.get("CI")),
        suppress_health_check=[HealthCheck.too_slow],
    )
    settings.register_profile("thorough", deadline=None, max_examples=500)
    settings.load_profile(os.environ["HYPOTHESIS_PROFILE"])
except ImportError:  # pragma: no cover
    pass


def pytest_sessionstart(session):
    """Once per run, before any test (with pytest-xdist: in its controller, before the workers start): the CPU
    kernels training calls, compiled into numba's disk cache by ``compile_ahead`` (one process per core), so the
    workers load them instead of each compiling them itself. Nothing to do when they are cached."""
    if hasattr(session.config, "workerinput"):
        return
    from meshsplat._numba import numba_available

    if numba_available():
        from meshsplat.train.cpu_kernels import compile_ahead

        compile_ahead(2)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture(scope="session")
def assets():
    return assets_dir()


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def standin_model_dir(tmp_path_factory, assets):
    """Stand-in SMPL / SMPL-X / FLAME model files (generated once per session; use as --model-dir)."""
    return write_standin_models(tmp_path_factory.mktemp("standin_models"))
