"""Shared fixtures. ``shared_data`` points at ``../shared/data`` beside the project; tests that need it are
marked ``shared_data`` and skipped on a fresh clone without it."""

from __future__ import annotations

import os
from pathlib import Path

# small-matrix BLAS is faster single-threaded (see magnav_ins/__init__.py); set before numpy is imported
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402 (after the BLAS environment)

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = PROJECT_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not beside the project")
    return SHARED_DATA


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(12345)
