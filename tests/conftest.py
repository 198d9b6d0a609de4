"""Shared test fixtures.

Tests that read the reference data in ``../shared/data`` (beside the checkout in CI; override
with ``TORCHFIT_SHARED``) skip cleanly where it is absent, as in a user's fresh clone.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
TEST_DATA = Path(__file__).resolve().parent / "data"


def shared_data_dir() -> Path | None:
    """The ``shared/data`` folder, or None where it is absent."""
    env = os.environ.get("TORCHFIT_SHARED")
    root = Path(env) if env else REPO_ROOT.parent / "shared"
    data = root / "data"
    return data if data.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ``../shared/data``; skips the test where it is absent."""
    path = shared_data_dir()
    if path is None:
        pytest.skip("../shared/data is not available (set TORCHFIT_SHARED to point at it)")
    return path


@pytest.fixture(scope="session")
def model():
    """The ``mpeg4_full`` template body (stateless, so one instance serves every test)."""
    from torchfit.body import BodyModel

    return BodyModel("mpeg4_full")
