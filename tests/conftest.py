"""Shared test configuration: float64 for accuracy tests, data paths, small scenes."""

from __future__ import annotations

import gc
import os
import shutil
import tempfile
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

# One persistent compilation cache per test session, shared by the xdist workers, notebook
# kernels and CLI subprocesses (they inherit the environment), so a program compiled by one
# process is loaded by the others instead of compiled again. The xdist controller imports this
# file before it starts the workers, so they inherit its folder; it is deleted when the session
# ends (pytest_unconfigure), so every run starts cold, as CI must. The cache key includes the
# program, the compile options and the jax/jaxlib version, so an edited function can never load
# a stale executable. A folder set by the user (JAX_COMPILATION_CACHE_DIR) is used as it is.
# Opt-in (JAXTRAJ_TEST_SHARED_CACHE=1): it cut CPU time, not the suite's wall time. (A worker
# once died inside jax's cache write; the cause was the mapping limit handled below.)
_SESSION_CACHE: str | None = None
if "JAX_COMPILATION_CACHE_DIR" not in os.environ and os.environ.get(
    "JAXTRAJ_TEST_SHARED_CACHE", "0"
) not in ("", "0"):
    _SESSION_CACHE = tempfile.mkdtemp(prefix="jaxtraj-test-jax-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _SESSION_CACHE
    # Cache every program: the defaults skip those that compile in under a second, which on
    # CPU are most of them.
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")
    # jax reads these variables when it is imported, which may have been before this file ran
    # (the workers and subprocesses import it after, with the variables set).
    jax.config.update("jax_compilation_cache_dir", _SESSION_CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


# XLA:CPU compiles the tests' programs without LLVM optimisation (-O0). Most of the suite's
# time is compilation of programs that then run once on tiny inputs: at -O0 the camera-pose
# fusion tests compile about 2.5x faster (31 -> 13 s for test_vmap_over_recordings_equals_loop's
# programs), and the results agree to rounding. The benchmarks, the demo and users' code keep
# XLA's default level; a level set by the user (in XLA_FLAGS) is kept.
_OPT_LEVEL = "--xla_backend_optimization_level"
if _OPT_LEVEL not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_OPT_LEVEL}=0".strip()

# jaxtraj sets its XLA_FLAGS when imported, which takes effect only before the process first
# compiles. Import it here, before any test module runs, so every executable this process puts
# in the shared cache was compiled with the flags that its cache key records.
import jaxtraj  # noqa: E402, F401


def pytest_unconfigure(config):
    """Delete this session's compilation cache (only in the process that created it)."""
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)


# Each compiled XLA:CPU executable keeps its code in a few memory mappings until jax drops it
# from its caches, and Linux allows a process 65530 mappings (vm.max_map_count). One xdist
# worker compiles over a thousand programs in a full run (test_estimators_smoothness.py alone
# took a process from 425 to 14324 mappings; jax.clear_caches() brought it back to 710), and
# past the limit LLVM's mmap fails and the worker dies with a segmentation fault inside a
# compile (three fresh-clone runs each lost one test that way). So after any test that
# leaves more than _MAX_MAPPINGS, the caches are cleared (later tests recompile what they use).
_MAPS = Path("/proc/self/maps")
_MAX_MAPPINGS = 25_000


def _mappings() -> int:
    try:
        with _MAPS.open("rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


@pytest.fixture(autouse=True)
def _bounded_compiled_code():
    yield
    if _mappings() > _MAX_MAPPINGS:
        jax.clear_caches()
        gc.collect()


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
