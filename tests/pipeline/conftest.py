"""Fixtures of the pipeline tests."""
from __future__ import annotations

import pytest

from _pipeline_data import DATA


@pytest.fixture(scope="session")
def mitsuba_available():
    if not (DATA / "frame_0000.exr").is_file():
        pytest.fail(f"sample data missing at {DATA}")
    return DATA
