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


# Modules whose tests share an expensive module-scoped fixture (a simulated recording, a
# designed camera path, a Monte-Carlo run) or compiled programs: under pytest-xdist each
# module is one unit of work (pytest_xdist_make_scheduler), so that the fixture is built
# once, not once per worker.
_GROUPED = (
    "test_pipeline_e2e.py",
    "test_cli_pipeline.py",
    "test_fusion_consistency.py",
    "test_design.py",
)

# The slowest items (tens of seconds each on 2 cores), started first so that no worker is
# left alone with one of them at the end. Notebook 04 runs the pipeline at the end-to-end
# test's sizes: started after it, it finds that test's programs in the compilation cache.
_SLOW_FIRST = (
    "test_pipeline_e2e.py",
    "test_notebooks.py::test_notebook_runs[05_camera_path_design.ipynb]",
    "test_cli_pipeline.py",
    "test_bench_design_smoke.py",
    "test_notebooks.py::test_notebook_runs[04_recording_walkthrough.ipynb]",
    "test_notebooks.py::test_notebook_runs[03_beyond_plain_dct.ipynb]",
    "test_scale.py::test_sharded_over_four_devices_equals_one_device",
    "test_fusion_eskf.py::test_vmap_over_recordings_equals_loop",
    "test_estimators_smoothness.py::test_gradient_matches_finite_differences",
    "test_notebooks.py::test_notebook_runs[02_camera_pose_fusion.ipynb]",
    "test_fusion_consistency.py",
    "test_design.py",
)


def _slow_rank(item) -> int:
    name = item.nodeid.split("/")[-1]
    for rank, prefix in enumerate(_SLOW_FIRST):
        if name == prefix or name.startswith(prefix + "::"):
            return rank
    return len(_SLOW_FIRST)


def pytest_collection_modifyitems(config, items):
    items.sort(key=_slow_rank)  # stable: the rest keep their order


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """pytest-xdist's default (``-n`` without ``--dist``): load scheduling in the order of
    the collection above, with each ``_GROUPED`` module as one unit of work."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SlowFirstGrouped(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            module = nodeid.split("::")[0]
            return module if module.split("/")[-1] in _GROUPED else nodeid

    config.option.loadscopereorder = False  # keep the slow-first order
    return SlowFirstGrouped(config, log)
