"""The ``denoise`` command against the code of an earlier commit: same machine, same run, interleaved.

    .venv/bin/python benchmarks/bench_against_commit.py [--commit 0ea1ee1] [--threads 1 2] [--rounds 3]

Issue 15 bounds the denoiser's per-frame cost at twice the command's when the issue was filed: commit
``0ea1ee1``, the parent of the first validation-set commit (its README gives the shared clip 31.00 dB). That
commit is checked out beside this tree (a detached git worktree in a temporary folder), its extension built
with this venv's torch, and each tree's ``torchmanifold denoise`` runs as a user runs it, in a fresh process,
on the clip's first 2 frames and on all N: ``(t_N - t_2) / (N - 2)`` is the cost of a frame without start-up.
Each round runs both trees at each thread count in turn, so a busy machine slows both alike; the figures are
medians over rounds. Writes ``results/against_commit.json``: per tree and thread count the ms per frame, the
2-frame run's seconds (start-up and two frames), the PSNR of the N outputs against the clip's references, and
this tree's time over the earlier one's.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
import harness  # noqa: E402

#: the code when issue 15 was filed (31.00 dB on the shared clip, as the issue says)
ISSUE_15_FILED = "0ea1ee1"


def _run(tree: Path, frames: list[Path], out: Path, threads: int) -> float:
    """Seconds of one ``torchmanifold denoise`` run of ``tree``'s code, start-up included."""
    cmd = [sys.executable, "-m", "torchmanifold.cli", "denoise", *map(str, frames), "--out", str(out),
           "--quiet", "--threads", str(threads), "--overwrite"]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True,
                          text=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{tree}: torchmanifold denoise failed:\n{done.stderr[-2000:]}")
    return seconds


def _psnr(out: Path, frames: list[Path]) -> float:
    """PSNR of the outputs in ``out`` (named as ``frames``) against the clip's ``reference_XXXX.exr``."""
    import torch

    from torchmanifold import metrics
    from torchmanifold.io.frames import read_render_frame

    def colour(p: Path) -> torch.Tensor:
        return torch.from_numpy(read_render_frame(p).color)

    outs = torch.stack([colour(out / f.name) for f in frames])
    refs = torch.stack([colour(f.parent / f"reference_{f.stem.split('_')[-1]}.exr") for f in frames])
    return float(metrics.psnr(outs.float(), refs.float()))


def _build_earlier_tree(commit: str, folder: Path) -> None:
    """``commit`` checked out in ``folder`` (a git worktree) with its extension built."""
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--force", str(folder), commit],
                   check=True, capture_output=True)
    built = subprocess.run([sys.executable, "setup.py", "build_ext", "--inplace"], cwd=folder,
                           capture_output=True, text=True)
    if built.returncode != 0:
        raise RuntimeError(f"building {commit}'s extension failed:\n{built.stderr[-2000:]}")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--commit", default=ISSUE_15_FILED)
    p.add_argument("--clip", type=Path, default=harness.DATA)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    frames = sorted(a.clip.glob("frame_0*.exr"))
    if len(frames) < 4:
        raise SystemExit(f"--clip {a.clip}: expected at least 4 frame_XXXX.exr, found {len(frames)}")
    missing = [f.name for f in frames if not (a.clip / f"reference_{f.stem.split('_')[-1]}.exr").exists()]
    if missing:
        raise SystemExit(f"--clip {a.clip}: expected a reference_XXXX.exr for each frame; none for {missing}")
    from tqdm import tqdm

    runs: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        earlier = Path(tmp) / "earlier"
        trees = {a.commit: earlier, "this tree": ROOT}
        try:
            _build_earlier_tree(a.commit, earlier)
            steps = [(r, th, name, n) for r in range(a.rounds) for th in a.threads for name in trees
                     for n in (2, len(frames))]
            outs = {name: Path(tmp) / f"out_{i}" for i, name in enumerate(trees)}
            for _, th, name, n in tqdm(steps, desc="runs"):
                runs.setdefault((name, th), {}).setdefault(n, []).append(
                    _run(trees[name], frames[:n], outs[name], th))
            psnr = {name: _psnr(out, frames) for name, out in outs.items()}  # the last run wrote all N
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(earlier)],
                           capture_output=True)
    res = {"commit": a.commit, "clip": str(a.clip), "frames": len(frames),
           "rounds": a.rounds, "trees": {}}
    for (name, th), t in runs.items():
        per_frame = [(tn - t2) / (len(frames) - 2) for t2, tn in zip(t[2], t[len(frames)])]
        res["trees"].setdefault(name, {"psnr": psnr[name]})[f"{th} threads"] = {
            "ms_per_frame": 1e3 * statistics.median(per_frame),
            "ms_per_frame_rounds": [1e3 * x for x in per_frame], "two_frame_run_s": statistics.median(t[2])}
    res["this_over_earlier"] = {f"{th} threads": res["trees"]["this tree"][f"{th} threads"]["ms_per_frame"]
                                / res["trees"][a.commit][f"{th} threads"]["ms_per_frame"] for th in a.threads}
    harness.write_json("against_commit", res)
    for name, r in res["trees"].items():
        print(f"{name}: {r['psnr']:.2f} dB; " + ", ".join(
            f"{k} {v['ms_per_frame']:.0f} ms a frame" for k, v in r.items() if k != "psnr"))
    print("this tree's time over the earlier one's: " +
          ", ".join(f"{k} {v:.2f}x" for k, v in res["this_over_earlier"].items()))
    return res


if __name__ == "__main__":
    main()
