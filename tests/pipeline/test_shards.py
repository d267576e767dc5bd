"""Frame-window shards on a local Ray cluster of 2 workers: the same bytes as the one-process path,
a killed worker costs a retry, a re-run resumes, bad input fails clearly.

One cluster for the module (starting one takes seconds); small clips.
"""
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from torchmanifold.cli import main
from torchmanifold.io import read_exr, write_exr
from torchmanifold.pipeline import shards
from torchmanifold.pipeline.denoise import DenoiseSettings
from torchmanifold.pipeline.render_job import render_query_times
from torchmanifold.pipeline.job import denoise_files, render_job
from torchmanifold.pipeline.progressive import PROGRESSIVE_FILTER

ray = pytest.importorskip("ray", reason="requirements.txt installs ray; the sharded engine needs it")

N_FRAMES = 7
RADIUS = 2  # chunks of 1 frame are shorter than the halo
RENDER = dict(frames=4, iterations=3, width=16, height=12, reference_spp=2, inbetween=1, seed=3)


@pytest.fixture(scope="module")
def kill_flag(tmp_path_factory):
    return tmp_path_factory.mktemp("fault") / "kill-one-worker"


@pytest.fixture(scope="module")
def cluster(kill_flag):
    # the workers inherit the environment: the fault hook is armed only while the flag file exists
    os.environ["TORCHMANIFOLD_SHARDS_KILL_FILE"] = str(kill_flag)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield
    ray.shutdown()
    del os.environ["TORCHMANIFOLD_SHARDS_KILL_FILE"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory, mitsuba_dir):
    """7 small frames whose brightness and position range differ per frame, so any statistic taken over
    more than a frame's window (scene extent, firefly floor) changes the result of a chunk."""
    src = tmp_path_factory.mktemp("clip")
    paths = []
    for k in range(N_FRAMES):
        d = read_exr(mitsuba_dir / f"frame_{k % 4:04d}.exr")
        d = {n: v[96:120, 96:128].copy() for n, v in d.items()}
        for n in "RGB":
            d[n] *= 1.0 + 0.5 * k
        for n in ("P.X", "P.Y", "P.Z", "Z"):
            d[n] *= 1.0 + 0.3 * k
        paths.append(write_exr(src / f"shot_{k:04d}.exr", d))
    return paths


@pytest.fixture(scope="module")
def denoise_reference(clip, tmp_path_factory):
    out = tmp_path_factory.mktemp("one") / "out"
    res = denoise_files(clip, out, settings=DenoiseSettings(temporal_radius=RADIUS), progress=False)
    return out, res


@pytest.fixture(scope="module")
def render_reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("one") / "render"
    render_job(out, progress=False, **RENDER)
    return out


def _same_files(a: Path, b: Path, names):
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


def test_plan_and_cone():
    c = shards.plan_chunks([0, 1, 2, 5, 6, 7, 8], 3, shards.denoise_halo(9, 2))
    assert [(x.owned, x.lo, x.hi) for x in c] == [((0, 1, 2), 0, 4), ((5, 6, 7), 3, 8), ((8,), 6, 8)]
    # frames 0..9, radius 1, 3 iterations: owned 4, 5 need 3..6 after iteration 2 and 2..7 after iteration 1
    times, query = render_query_times(10, 0)
    keep, lo, hi = shards.render_cone(times, query, [4, 5], 1, 3)
    assert keep == [list(range(2, 8)), list(range(2, 8)), list(range(3, 7))]
    assert (lo, hi) == (1, 8)
    with pytest.raises(ValueError, match="chunk must be an integer >= 1"):
        shards.plan_chunks([0], 0, shards.denoise_halo(1, 0))


@pytest.mark.parametrize("chunk", [1, 3])
def test_denoise_sharded_is_bitwise_one_process(cluster, clip, denoise_reference, tmp_path, chunk):
    ref_out, ref = denoise_reference
    res = shards.shard_denoise(clip, tmp_path / "out", settings=DenoiseSettings(temporal_radius=RADIUS),
                               chunk=chunk, progress=False)
    _same_files(ref_out, tmp_path / "out", [p.name for p in clip])
    for k in ("frames", "size", "feature_channels", "nonfinite_samples", "nonfinite_color", "nonfinite_features",
              "firefly_energy_removed", "noisy_sky_frames", "kept_flat_frames",
              "samples_per_pixel", "sigma_s", "footprint_sigma"):
        assert res[k] == ref[k], k
    s = res["shards"]
    assert s["chunks"] == -(-N_FRAMES // chunk) and s["written"] == N_FRAMES and s["retries"] == 0
    # owned frames + the halo each chunk reads (clipped at the clip's ends): the frames a query's output
    # depends on (its filter's, its albedo's and its evidence's windows)
    halo = DenoiseSettings(temporal_radius=RADIUS).window_radius
    assert s["frames_read"] == sum(c.hi - c.lo + 1 for c in shards.plan_chunks(
        range(N_FRAMES), chunk, shards.denoise_halo(N_FRAMES, halo)))
    assert sum(w["frames"] for w in s["workers"].values()) == N_FRAMES
    m = json.loads((tmp_path / "out" / shards.MANIFEST).read_text())
    for t, p in enumerate(clip):
        rec = m["done"][str(t)]["files"][p.name]
        assert rec["bytes"] == (ref_out / p.name).stat().st_size


@pytest.mark.parametrize("chunk", [1, 3])
def test_render_sharded_is_bitwise_one_process(cluster, render_reference, tmp_path, capsys, chunk):
    out = tmp_path / "render"
    args = ["render", "--out", str(out), "--quiet", "--engine", "ray", "--chunk", str(chunk)]
    for k, v in RENDER.items():
        args += ["--" + k.replace("_", "-"), str(v)]
    assert main(args) == 0, capsys.readouterr().err
    res = json.loads(capsys.readouterr().out)
    q = len(res["query_times"])
    assert q == 7
    names = [f"frames/frame_{i:04d}.exr" for i in range(q)] + [f"png/frame_{i:04d}.png" for i in range(q)]
    _same_files(render_reference, out, names)
    s = res["shards"]
    times, query = render_query_times(RENDER["frames"], RENDER["inbetween"])
    plan = shards.plan_chunks(range(q), chunk, lambda o: (0, 0))
    # the halo's cost: the engine renders exactly the planned cone of every chunk (a query reads the frames
    # of its filter's window and of its evidence-lending neighbours')
    r = DenoiseSettings(**PROGRESSIVE_FILTER).query_radius
    assert s["frames_traced"] == sum(shards.traced_frames(
        times, query, shards.render_cone(times, query, c.owned, r, RENDER["iterations"])[0], r) for c in plan)
    assert s["frames_traced"] >= s["frames_traced_one_process"] == RENDER["iterations"] * RENDER["frames"]


def test_colour_alone_sharded_is_bitwise_one_process(cluster, clip, tmp_path):
    """Colour alone takes its own settings (narrower candidates, each frame also alone) in the sharded path
    too: the same bytes as one process."""
    paths = []
    for p in clip:
        d = read_exr(p)
        paths.append(write_exr(tmp_path / p.name, {c: d[c] for c in "RGB"}))
    settings = DenoiseSettings(temporal_radius=RADIUS)
    one = denoise_files(paths, tmp_path / "one", settings=settings, progress=False)
    assert any("each frame also filtered alone" in n for n in one["notes"])
    shards.shard_denoise(paths, tmp_path / "sharded", settings=settings, chunk=3, progress=False)
    _same_files(tmp_path / "one", tmp_path / "sharded", [p.name for p in paths])


def test_killed_worker_costs_a_retry_not_a_frame(cluster, clip, denoise_reference, kill_flag, tmp_path):
    ref_out, _ = denoise_reference
    kill_flag.write_text("")
    res = shards.shard_denoise(clip, tmp_path / "out", settings=DenoiseSettings(temporal_radius=RADIUS),
                               chunk=3, progress=False)
    assert not kill_flag.exists(), "no worker died"
    assert len(list(kill_flag.parent.glob(kill_flag.name + ".claimed-*"))) == 1
    s = res["shards"]
    assert s["retries"] == 1
    # every frame was reported written exactly once: the retry skipped what the dead attempt had written
    assert s["reports"] == N_FRAMES
    _same_files(ref_out, tmp_path / "out", [p.name for p in clip])
    assert not list((tmp_path / "out").glob("*.tmp"))


def test_unreadable_frame_stops_and_rerun_resumes(cluster, clip, denoise_reference, tmp_path):
    ref_out, _ = denoise_reference
    src = tmp_path / "in"
    src.mkdir()
    paths = []
    for p in clip:
        (src / p.name).write_bytes(p.read_bytes())
        paths.append(src / p.name)
    bad = paths[-1]
    bad.write_bytes(b"not an exr" * 100)
    out = tmp_path / "out"
    settings = DenoiseSettings(temporal_radius=RADIUS)
    with pytest.raises(ValueError, match="not a readable EXR") as e:
        shards.shard_denoise(paths, out, settings=settings, chunk=1, progress=False)
    assert str(bad) in str(e.value)
    m = json.loads((out / shards.MANIFEST).read_text())
    done = sorted(int(k) for k in m["done"])
    # frames whose window holds the bad file never finish; the finished ones are complete and listed
    assert done and not set(done) & set(range(N_FRAMES - 1 - RADIUS, N_FRAMES))
    _same_files(ref_out, out, [clip[t].name for t in done])
    unlisted = {p.name for p in out.glob("*.exr")} - {clip[t].name for t in done}
    for n in unlisted:  # written after the stop was decided: still whole, rewritten by the re-run
        assert (out / n).read_bytes() == (ref_out / n).read_bytes()

    bad.write_bytes(clip[-1].read_bytes())
    s = shards.shard_denoise(paths, out, settings=settings, chunk=1, progress=False)["shards"]
    assert s["skipped"] == len(done) and s["written"] == N_FRAMES - len(done)
    _same_files(ref_out, out, [p.name for p in clip])


def test_bad_chunk_and_address_without_engine(clip, tmp_path, capsys):
    for bad in ("0", "-2", "1.5", "x"):
        with pytest.raises(SystemExit) as e:
            main(["denoise", str(clip[0]), "--out", str(tmp_path / "o"), "--engine", "ray", "--chunk", bad])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "--chunk" in err and "integer number of frames >= 1" in err
    assert main(["denoise", str(clip[0]), "--out", str(tmp_path / "o"), "--chunk", "2"]) == 2
    assert "--engine ray" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_without_ray_installed(clip, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now fails as if it were not installed
    assert main(["denoise", str(clip[0]), "--out", str(tmp_path / "o"), "--engine", "ray", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "'ray'" in err and "pip install ray==" in err
    assert not (tmp_path / "o").exists()
    # the default engine never imports it
    assert main(["denoise", str(clip[0]), "--out", str(tmp_path / "o"), "--quiet"]) == 0


def test_address_that_does_not_answer(clip, tmp_path):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "o"
    code = ("import sys; from torchmanifold.cli import main; sys.exit(main(sys.argv[1:]))")
    p = subprocess.run([sys.executable, "-c", code, "denoise", str(clip[0]), "--out", str(out), "--engine", "ray",
                        "--address", f"127.0.0.1:{port}", "--quiet"],
                       capture_output=True, text=True, timeout=120, env={**os.environ})
    assert p.returncode == 2, p.stderr
    assert f"127.0.0.1:{port}" in p.stderr and "no Ray cluster answers" in p.stderr
    assert not out.exists()
