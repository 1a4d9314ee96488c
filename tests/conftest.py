"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

from experiments.datadir import DEFAULT_DATA_DIR, shared_data_dir

# One BLAS thread for the whole suite (as the CLI does): many small fits, where BLAS threads
# on a 2-core machine only contend.
threadpool_limits(limits=1, user_api="blas")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = shared_data_dir() or DEFAULT_DATA_DIR  # GYROHARNESS_DATA, else ../shared/data


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real measured recordings (../shared/data); tests that need them skip if absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} not present")
    return SHARED_DATA
