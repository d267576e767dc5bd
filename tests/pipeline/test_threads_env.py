"""Thread settings of the CLI: every core by default, OpenMP workers that sleep instead of spinning
(benchmarks/bench_threads.py measured spinning workers making two threads 4-10x slower than one)."""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _policy_after_import(env_policy):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("OMP_WAIT_POLICY", None)
    if env_policy is not None:
        env["OMP_WAIT_POLICY"] = env_policy
    code = "import os, torchmanifold; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_import_sets_passive_wait_policy_unless_the_user_set_one():
    assert _policy_after_import(None) == "PASSIVE"
    assert _policy_after_import("ACTIVE") == "ACTIVE"


def test_threads_default_to_every_core():
    from torchmanifold.cli import build_parser

    args = build_parser().parse_args(["denoise", "a.exr", "--out", "o"])
    assert args.threads == len(os.sched_getaffinity(0))
    assert build_parser().parse_args(["denoise", "a.exr", "--out", "o", "--threads", "1"]).threads == 1
