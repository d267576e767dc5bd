"""The stability suite runs the methods of ``benchmarks/baselines.py`` (the one method registry)."""
import sys
from pathlib import Path

_BENCH = str(Path(__file__).resolve().parents[2] / "benchmarks")
if _BENCH not in sys.path:
    sys.path.insert(0, _BENCH)
