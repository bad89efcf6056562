"""Fixtures of the solver's unit tests."""

from __future__ import annotations

import pytest
import warp as wp


@pytest.fixture
def cuda():
    """The CUDA device as warp's default for the test (skipped where none is present)."""
    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device")
    with wp.ScopedDevice("cuda"):
        yield wp.get_device("cuda")
