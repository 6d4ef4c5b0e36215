"""Shared test configuration: float64 for accuracy tests, data paths, small scenes."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

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
