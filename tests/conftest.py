"""Shared test configuration: float64 for accuracy tests, data paths, small scenes."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

#: Set by the process that created this session's compilation cache (and removes it).
_OWN_CACHE = "_jaxtraj_own_compilation_cache"


def pytest_configure(config):
    """One persistent XLA compilation cache for the whole test session.

    The pipeline (simulate -> fuse -> reconstruct) runs in the end-to-end test, the CLI
    tests and notebook 04, in different processes (pytest-xdist workers, notebook kernels,
    subprocesses), at the same array shapes; each would compile the same programs again.
    The cache is a fresh temporary folder per session (so every run still compiles
    everything once), shared through ``JAX_COMPILATION_CACHE_DIR``: set here, before
    pytest-xdist starts its workers, it is inherited by them and by everything they
    start. A folder the user set already is used as it is and kept.
    """
    folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not folder:
        folder = tempfile.mkdtemp(prefix="jaxtraj-test-xla-cache-")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
        setattr(config, _OWN_CACHE, folder)
    jax.config.update("jax_compilation_cache_dir", folder)


def pytest_unconfigure(config):
    folder = getattr(config, _OWN_CACHE, None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


#: ``../shared/data`` beside the checkout (present in CI, absent in users' clones).
SHARED_DATA = Path(
    os.environ.get("JAXTRAJ_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)


@pytest.fixture
def shared_data() -> Path:
    """The reference-data folder; skips the test with a reason when it is absent."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("JAXTRAJ_REQUIRE_DATA"):
            pytest.fail(f"JAXTRAJ_REQUIRE_DATA is set but {SHARED_DATA} does not exist")
        pytest.skip(
            f"reference data not found at {SHARED_DATA} (only CI and development checkouts "
            "have ../shared/data; set JAXTRAJ_SHARED_DATA to point elsewhere)"
        )
    return SHARED_DATA


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261123)
