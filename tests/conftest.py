"""Shared test configuration: float64 for accuracy tests, data paths, small scenes."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
import pytest

try:
    import fcntl
except ImportError:  # not POSIX: every worker builds its own copy
    fcntl = None

jax.config.update("jax_enable_x64", True)

# One BLAS thread per process (also for notebook kernels and subprocesses): pytest-xdist
# already runs a worker per core, and OpenBLAS threads that wait for a busy core spin (a
# 480 x 36 QR inside a jit-compiled solve took 350 ms instead of 0.5 ms on a loaded machine).
# SciPy's OpenBLAS, which JAX's LAPACK calls use, is loaded later and reads this.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

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


@pytest.fixture(scope="session")
def build_once(tmp_path_factory) -> Callable[[str, Callable[[Path], None]], Path]:
    """``build_once(name, build)``: a folder filled by ``build(folder)`` once per session.

    Under pytest-xdist the workers share one build: the first worker to ask builds it under
    a file lock, the others wait for it and reuse it (simulating a recording and compiling
    the pipeline take minutes). A build that raised is redone by the next worker to ask.
    Tests must treat the folder as read-only (copy it before changing it).
    """

    def get(name: str, build: Callable[[Path], None]) -> Path:
        if fcntl is None or not os.environ.get("PYTEST_XDIST_WORKER"):
            folder = tmp_path_factory.mktemp(name)
            build(folder)
            return folder
        root = tmp_path_factory.getbasetemp().parent / f"{name}_shared"
        root.mkdir(exist_ok=True)
        folder = root / "data"
        with open(root / "lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (root / "done").exists():
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir()
                build(folder)
                (root / "done").touch()
        return folder

    return get
