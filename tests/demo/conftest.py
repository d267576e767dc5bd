"""Fixtures of the demo tests. The demo package lives at the repository root (not installed)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# demo.app imports torch._dynamo (when triton is there) before the window makes a GL context.
import demo.app  # noqa: E402,F401
from _demo_helpers import SMALL  # noqa: E402


@pytest.fixture(scope="module")
def headless_run(tmp_path_factory):
    """The real WindowConfig, headless (EGL): 3 frames = 3 iterations of the progressive engine, then a
    screenshot and the stats file (beside it, ``shot.json``)."""
    from demo.app import run

    shot = tmp_path_factory.mktemp("demo") / "shot.png"
    app = run(SMALL + ["--headless", "--frames", "3", "--screenshot", str(shot), "--stats", str(shot.with_suffix(".json"))])
    return app, shot
