"""Thread settings: the CLI uses every core by default, ``--threads`` sets llvmpipe's threads as well as
torch's, OpenMP workers sleep instead of spinning
(benchmarks/bench_threads.py measured spinning workers making two threads 4-10x slower than one), and a
pipeline entry point runs its glue on one thread and hands the caller's threads to the ops it calls."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchmanifold._threads import call_parallel, serial, torch_threads

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


def _tracer_threads(threads, lp_env):
    """The llvmpipe rasterizer threads (named llvmpipe-N) of a process that took ``threads`` cores the way
    the CLI does and then traced two frames, with LP_NUM_THREADS ``lp_env`` (None: unset) in its
    environment, and the digest of what it traced."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("LP_NUM_THREADS", None)
    if lp_env is not None:
        env["LP_NUM_THREADS"] = lp_env
    code = f"""
import os, torch, torchmanifold
from torchmanifold._threads import set_threads
from torchmanifold.render import PathTracer, default_scene
set_threads({threads})
assert torch.get_num_threads() == {threads}
import hashlib
r = PathTracer(default_scene(), 24, 16).render(times=[0.0, 1.0], spp=2, seed=5)
names = [open(f"/proc/self/task/{{t}}/comm").read().strip() for t in os.listdir("/proc/self/task")]
digest = hashlib.sha256(b"".join(x.numpy().tobytes() for x in (r.color, r.features, r.emission))).hexdigest()
print(sum(n.startswith("llvmpipe") for n in names), digest)
"""
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    count, digest = out.stdout.strip().splitlines()[-1].split()
    return int(count), digest


def test_threads_set_the_tracers_rasterizer_threads_unless_the_user_did():
    # llvmpipe takes one thread per core by default: a one-thread job traced on every core
    runs = {key: _tracer_threads(*key) for key in [(1, None), (3, None), (1, "2")]}
    assert {key: n for key, (n, _) in runs.items()} == {(1, None): 1, (3, None): 3, (1, "2"): 2}
    # the frames do not depend on how many threads trace them
    assert len({digest for _, digest in runs.values()}) == 1


def test_serial_glue_and_parallel_ops():
    seen = {}

    @serial
    def step():
        seen["glue"] = torch.get_num_threads()
        seen["op"] = call_parallel(torch.get_num_threads)
        seen["nested"] = serial(lambda: call_parallel(torch.get_num_threads))()

    with torch_threads(2):
        step()
        assert torch.get_num_threads() == 2
    assert seen == {"glue": 1, "op": 2, "nested": 2}
    with torch_threads(2):
        assert call_parallel(torch.get_num_threads) == 2  # outside an entry point: unchanged


def test_counts_restored_after_an_error():
    @serial
    def fails():
        call_parallel(lambda: (_ for _ in ()).throw(RuntimeError("op failed")))

    with torch_threads(2):
        with pytest.raises(RuntimeError, match="op failed"):
            fails()
        assert torch.get_num_threads() == 2
        assert call_parallel(torch.get_num_threads) == 2


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_in_order_pool_hands_results_back_in_submission_order(threads):
    import time

    from torchmanifold._threads import InOrder

    def work(k):
        time.sleep(0.02 if k % 3 == 0 else 0.0)  # early calls finish last
        return k * k, torch.get_num_threads()

    got = []
    with InOrder(threads, 7) as pool:
        for k in range(7):
            got += pool.submit(k, work, k)
        got += pool.drain()
    assert [k for k, _ in got] == list(range(7)) and [r for _, (r, _) in got] == [k * k for k in range(7)]
    assert {n for _, (_, n) in got} == ({torch.get_num_threads()} if threads == 1 else {threads // min(threads, 7)})


def test_in_order_pool_raises_a_worker_error():
    from torchmanifold._threads import InOrder

    def work(k):
        if k == 2:
            raise ValueError("frame 2 is bad")
        return k

    with pytest.raises(ValueError, match="frame 2"):
        with InOrder(2, 5) as pool:
            for k in range(5):
                pool.submit(k, work, k)
            pool.drain()


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_in_order_calls_wait_on_calls_started_ahead(threads):
    """Calls started ahead (a clip's frames prepared) and ordered calls that wait on them (its windows
    filtered): every worker busy waiting never starves the calls it waits on, results come in order, and
    an error of a call started ahead is raised where its result is taken."""
    import time

    from torchmanifold._threads import InOrder

    def prepare(k, bad):
        time.sleep(0.01 * (k % 2))
        if k == bad:
            raise ValueError(f"frame {k} is bad")
        return 10 * k

    def window(futures):
        return sum(f.result() for f in futures)

    def run(bad):
        got, ahead = [], {}
        with InOrder(threads, 8) as pool:
            for t in range(8):
                ids = range(max(0, t - 1), min(8, t + 2))
                for k in ids:
                    if k not in ahead:
                        ahead[k] = pool.ahead(prepare, k, bad)
                got += pool.submit(t, window, [ahead[k] for k in ids])
            got += pool.drain()
        return got

    assert run(None) == [(t, sum(10 * k for k in range(max(0, t - 1), min(8, t + 2)))) for t in range(8)]
    with pytest.raises(ValueError, match="frame 6"):
        run(6)
