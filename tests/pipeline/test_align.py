"""The time window brought to the query frame's pixels by matching the samples' features
(torchmanifold.pipeline.align)."""
import pytest
import torch
from _pipeline_data import validation_clip

from torchmanifold import metrics as M
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline import align as A
from torchmanifold.pipeline.denoise import DenoiseSettings, denoise_frames


def _offsets(flow: A.Flow, H: int, W: int) -> tuple[torch.Tensor, torch.Tensor]:
    index = flow.index.view(H, W)
    return index // W - torch.arange(H)[:, None], index % W - torch.arange(W)[None, :]


def _room(H: int, W: int, shift: tuple[float, float] = (0.0, 0.0), seed: int = 0) -> torch.Tensor:
    """World positions ``(3, H, W)`` of a view of a back wall (depth 4) and a floor ramp below it, the view
    moved by ``shift`` pixels, each position one sample jittered within its pixel."""
    g = torch.Generator().manual_seed(seed)
    jitter = torch.rand(2, H, W, generator=g, dtype=torch.float64)
    y = torch.arange(H, dtype=torch.float64)[:, None] + shift[0] + jitter[0]
    x = torch.arange(W, dtype=torch.float64)[None, :] + shift[1] + jitter[1]
    u, v = (x - W / 2) / W, (y - H / 2) / H  # image-plane coordinates
    depth = torch.where(v < 0.1, torch.full_like(v, 4.0), 0.4 / (v - 0.1 + 0.1 / 4))  # wall, then floor
    return torch.stack([u * depth, -v * depth, depth]).float()


@pytest.mark.parametrize("shift", [(0, 5), (-3, 2), (4, -7)])
def test_the_flow_finds_a_moved_view(shift):
    """A view moved by whole pixels: every pixel whose surface the other frame still shows finds it there."""
    H, W = 48, 64
    to, source = _room(H, W, seed=1), _room(H, W, shift, seed=2)
    flow = A.frame_flow(to, source)
    dy, dx = _offsets(flow, H, W)
    ys, xs = torch.arange(H)[:, None] - shift[0], torch.arange(W)[None, :] - shift[1]
    beyond = (ys < 0) | (ys >= H) | (xs < 0) | (xs >= W)  # what the other frame does not show
    found = (dy == -shift[0]) & (dx == -shift[1])
    assert float(found[~beyond].float().mean()) > 0.97
    assert bool(flow.inside[~beyond].all())


def test_a_still_view_keeps_its_pixels():
    """Two frames of a still view (each sample jittered anew): no flow, so the window stays as it was."""
    assert A.frame_flow(_room(40, 40, seed=3), _room(40, 40, seed=4)) is None


def test_two_frames_apart_the_search_reaches_twice_as_far():
    """A pan of 7 px a frame, seen two frames apart: 14 px, beyond one frame's reach."""
    H, W = 64, 64
    flow = A.frame_flow(_room(H, W, seed=5), _room(H, W, (0, 14), seed=6), distance=2)
    dy, dx = _offsets(flow, H, W)
    assert float(((dy == 0) & (dx == -14))[:, 14:].float().mean()) > 0.97  # the other frame shows x >= 14


def test_surfaces_that_move_apart_each_find_their_own():
    """Parallax: the wall moves one way and the near floor the other; the floor's pixels follow their own
    surface, not the frame's dominant offset. (Near the horizon the floor's positions change too fast for its
    match to beat the dominant one clearly: there it keeps that.)"""
    H, W = 64, 64
    to = _room(H, W, seed=7)
    floor = torch.arange(H)[:, None].expand(H, W) >= 40
    source = torch.where(floor, _room(H, W, (0, -3), seed=9), _room(H, W, (0, 2), seed=8))
    dy, dx = _offsets(A.frame_flow(to, source), H, W)
    assert float(((dy == 0) & (dx == -2))[4:36, 4:].float().mean()) > 0.97  # the wall
    assert float(((dy == 0) & (dx == 3))[56:, 4:-4].float().mean()) > 0.8  # the near floor


def _checker_room(H: int, W: int, shift: tuple[int, int] = (0, 0)) -> torch.Tensor:
    """Features without positions ``(7, H, W)``: a checkered albedo on a wall (24 px squares), its plain
    normal and depth, the view moved by ``shift`` pixels."""
    y = torch.arange(H)[:, None] + shift[0]
    x = torch.arange(W)[None, :] + shift[1]
    white = ((y // 24 + x // 24) % 2 == 0).float().expand(H, W)
    albedo = torch.stack([0.2 + 0.6 * white, 0.3 + 0.4 * white, 0.5 - 0.2 * white])
    normal = torch.stack([torch.zeros(H, W), torch.zeros(H, W), torch.ones(H, W)])
    return torch.cat([albedo, normal, torch.full((1, H, W), 4.0)])


def test_piecewise_constant_features_find_the_move_where_they_vary():
    """Without world positions: on a checkered wall a 5 px move leaves most pixels inside their square, where
    no move matches as well as the true one, so the median over every pixel keeps the view still; over the
    pixels where the features vary (the squares' edges), the move is found."""
    H, W = 48, 64
    to, source = _checker_room(H, W), _checker_room(H, W, (0, 5))
    assert A.frame_flow(to, source) is None
    dy, dx = _offsets(A.frame_flow(to, source, varying_only=True), H, W)
    assert float(((dy == 0) & (dx == -5))[:, 5:].float().mean()) > 0.97


@pytest.mark.parametrize("varying_only", [False, True])
def test_a_window_finds_each_pairs_flow_as_alone(monkeypatch, varying_only):
    """The window's flows, each frame's side made once for all its pairs, are :func:`frame_flow`'s of each
    pair alone, index for index, in a still window and a panning one."""
    H, W = 40, 48
    for pan in (0, 3):
        frames = [_checker_room(H, W, (0, pan * t)) if varying_only else _room(H, W, (0, pan * t), seed=t)
                  for t in range(4)]
        made = []
        surface = A._surface
        monkeypatch.setattr(A, "_surface", lambda to, v: made.append(1) or surface(to, v))
        window = A.WindowAlignment(torch.stack(frames), [0.0, 1.0, 2.0, 3.0], 2, varying_only=varying_only)
        pairs = [(k, j) for k in range(4) for j in range(4) if 0 < abs(k - j) <= 2]
        flows = [window.flow(k, j) for k, j in pairs]
        assert len(made) == 4
        monkeypatch.setattr(A, "_surface", surface)
        for (k, j), flow in zip(pairs, flows):
            alone = A.frame_flow(frames[k], frames[j], abs(k - j), varying_only)
            assert (flow is None) == (alone is None) == (pan == 0)
            if flow is not None:
                assert torch.equal(flow.index, alone.index) and torch.equal(flow.inside, alone.inside)


def test_the_fused_kernels_match_pytorch():
    """The C++ cost kernels against the PyTorch steps they mirror: the same offsets, costs to rounding."""
    H, W = 37, 53
    to, source = _room(H, W, seed=10), _room(H, W, (2, -3), seed=11)
    g = torch.Generator().manual_seed(0)
    dy, dx = torch.randint(-4, 5, (H, W), generator=g), torch.randint(-4, 5, (H, W), generator=g)
    offsets = A._square(2)
    ys, xs = torch.randint(0, H, (300,), generator=g), torch.randint(0, W, (300,), generator=g)
    far = offsets + [(0, 60)]  # beyond the frame for every grid pixel: no median
    fused = A._least_cost(to, source, dy, dx, offsets), A._median_costs(to, source, ys, xs, far)
    with _fast.reference():
        plain = A._least_cost(to, source, dy, dx, offsets), A._median_costs(to, source, ys, xs, far)
    assert torch.equal(fused[0][0], plain[0][0]) and torch.equal(fused[0][1], plain[0][1])
    torch.testing.assert_close(fused[0][2], plain[0][2], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fused[1], plain[1], rtol=1e-6, atol=0.0)
    assert fused[1][-1] == float("inf")



@pytest.mark.parametrize("pool", [7, 5])
def test_the_cost_kernel_matches_pytorch_on_moves_in_runs(monkeypatch, pool):
    """Offsets that are constant over blocks (a coarse level's upsampled to a finer one), some reaching
    beyond the frame: the kernel reads rows of long runs run by run and rows of short runs pixel by pixel,
    and pools 7x7 in one vector pass per row (5x5 in the general one); its offsets match PyTorch's, its
    costs to rounding, and its bytes are the same on one and two threads (tasks of whole rows)."""
    monkeypatch.setattr(A, "_POOL", pool)
    H, W = 96, 160
    to, source = _room(H, W, seed=12), _room(H, W, (3, -2), seed=13)
    g = torch.Generator().manual_seed(1)
    coarse = torch.randint(-6, 7, (2, H // 4, W // 16), generator=g)
    long_runs = coarse.repeat_interleave(4, 1).repeat_interleave(16, 2)  # rows of 10 runs: run by run
    short_runs = torch.randint(-3, 4, (2, H, W // 2), generator=g).repeat_interleave(2, 2)  # pixel by pixel
    rows = (torch.arange(H) % 3 == 0)[:, None]
    dy, dx = torch.where(rows, short_runs, long_runs)
    offsets = A._square(1)
    fused = A._least_cost(to, source, dy, dx, offsets)
    with _fast.reference():
        plain = A._least_cost(to, source, dy, dx, offsets)
    assert torch.equal(fused[0], plain[0]) and torch.equal(fused[1], plain[1])
    torch.testing.assert_close(fused[2], plain[2], rtol=1e-5, atol=1e-6)
    assert bool((fused[2] == A._OUTSIDE).any())  # some pixels' every source lies outside the frame
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = A._least_cost(to, source, dy, dx, offsets)
        torch.set_num_threads(2)
        two = A._least_cost(to, source, dy, dx, offsets)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_the_median_kernel_skips_only_offsets_outside_the_least():
    """With ``keep``, the median kernel leaves out offsets whose median lies above ``keep`` exact ones: the
    ``keep`` least (by median, then order) and their medians are those of the exact call, every offset left
    out (inf) has an exact median above the ``keep``-th least, most of a wide search is left out, and the
    bytes are the same on one and two threads."""
    H, W = 64, 64
    to, source = _room(H, W, seed=20), _room(H, W, (1, 2), seed=21)
    g = torch.Generator().manual_seed(2)
    ys, xs = torch.randint(0, H, (600,), generator=g), torch.randint(0, W, (600,), generator=g)
    offsets = A._square(8)
    exact = A._median_costs(to, source, ys, xs, offsets)
    some = A._median_costs(to, source, ys, xs, offsets, keep=9)
    least = sorted(range(len(offsets)), key=lambda i: (float(exact[i]), i))[:9]
    assert least == sorted(range(len(offsets)), key=lambda i: (float(some[i]), i))[:9]
    assert torch.equal(some[least], exact[least])
    out = torch.isinf(some) & torch.isfinite(exact)
    assert int(out.sum()) > len(offsets) // 2
    assert bool((exact[out] > exact[least].max()).all())
    assert torch.equal(some[~out], exact[~out])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = A._median_costs(to, source, ys, xs, offsets, keep=9)
        torch.set_num_threads(2)
        two = A._median_costs(to, source, ys, xs, offsets, keep=9)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)

# ------------------------------------------------------------------------------------------ in the denoiser
NAMES = ["albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z", "P.X", "P.Y", "P.Z"]


def _sunlit_wall(frames: int, pan: int, seed: int = 0, H: int = 48, W: int = 64):
    """A plain wall whose sunlit part no feature shows (a slanted border fixed on the wall), seen by a camera
    that pans ``pan`` px a frame; 1 spp, each sample the light times an exponential variate. Returns colour
    and features."""
    g = torch.Generator().manual_seed(seed)
    y = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    color, feats = [], []
    for t in range(frames):
        x = torch.arange(W, dtype=torch.float32)[None, :] + pan * t
        jx, jy = torch.rand(H, W, generator=g), torch.rand(H, W, generator=g)
        X, Y = (x + jx) / 16, (y + jy) / 16  # the wall's coordinates of each sample
        light = torch.where(X + 0.3 * Y < 3.0, 0.5, 0.075)
        noise = -torch.log(torch.rand(H, W, generator=g).clamp_min(1e-7))
        albedo = torch.full((3, H, W), 0.5)
        color.append((albedo * light * noise))
        normal = torch.stack([torch.zeros(H, W), torch.zeros(H, W), torch.ones(H, W)])
        feats.append(torch.cat([albedo, normal, torch.stack([X, Y, torch.full((H, W), 4.0)])]))
    return torch.stack(color), torch.stack(feats)


@pytest.mark.parametrize("clip", ["mi_dark_glossy", "mi_glass_mirror", "bl_glass_caustic"])
def test_a_panning_view_is_denoised_closer_to_its_reference(clip):
    """Clips of the validation set whose camera pans 3-6 px a frame (glossy highlights, what a mirror shows:
    nothing in the features keeps another frame's sample of another point apart), two from Mitsuba with world
    positions, one from Cycles without. Brought to the query's pixels, the window's frames agree: +0.32,
    +0.35 and +0.23 dB over frames 1-5 from 1 spp."""
    c, f, names, ref = validation_clip(clip, [1, 2, 3, 4, 5])
    psnr = {aligned: M.psnr(denoise_frames(c, f, names, samples_per_pixel=1, settings=DenoiseSettings(
        temporal_radius=1, align_frames=aligned)), ref) for aligned in (False, True)}
    assert psnr[True] > psnr[False] + 0.1, psnr


def test_a_still_view_is_filtered_as_without_alignment():
    """Nothing moves: the flows find no offset and every byte is as with ``align_frames=False``."""
    c, f = _sunlit_wall(4, pan=0)
    kw = dict(temporal_radius=1)
    on = denoise_frames(c, f, NAMES, settings=DenoiseSettings(**kw), samples_per_pixel=1)
    off = denoise_frames(c, f, NAMES, settings=DenoiseSettings(align_frames=False, **kw), samples_per_pixel=1)
    assert torch.equal(on, off)


def test_every_front_end_aligns_alike():
    """The clip in one call, each frame side by side, and one query at a time give the same bytes: a query's
    window and its neighbours' lent evidence are brought to its pixels whichever call filters them."""
    c, f = _sunlit_wall(6, pan=3, seed=1)
    st = DenoiseSettings(temporal_radius=1)
    whole = denoise_frames(c, f, NAMES, settings=st, samples_per_pixel=1)
    one_by_one = torch.cat([denoise_frames(c, f, NAMES, settings=st, samples_per_pixel=1,
                                           query_times=[float(t)]) for t in range(6)])
    assert torch.equal(whole, one_by_one)
