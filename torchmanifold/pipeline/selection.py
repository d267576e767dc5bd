"""Each pixel's bandwidth from the data: the filter runs at several bandwidths and every pixel blends them by
their error, estimated by cross-validation between two checkerboard halves of the samples (Rousselle et al.
2012), a bandwidth weighed by the likelihood that its error in excess of the least one's is noise. Where a
renderer's reconstruction filter shares samples between neighbouring pixels, the halves are squares of
pixels (:func:`_cv_cell`)."""
from __future__ import annotations

import math
import threading
from concurrent.futures import Future
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Sequence

import torch
from torch import Tensor

from torchmanifold import features as feature_table
from torchmanifold.pipeline import _fast
from torchmanifold.pipeline.filter import (_Filter, _frames, _halves, _halves_stack, _split_halves,
                                           tree_height_at)
from torchmanifold.pipeline.footprint import _normalised_blur
from torchmanifold.pipeline.image import (_LOG_RADIANCE_OFFSET, _frame_mean, _gaussian_taps, footprint_blur,
                                          luminance)
from torchmanifold.timewindow import frame_at, window, windows_span

if TYPE_CHECKING:
    from torchmanifold.pipeline.align import WindowAlignment
    from torchmanifold.pipeline.denoise import DenoiseSettings


#: a bandwidth whose pooled cross-validated error is over this many times the least one's is left out,
#: whatever the evidence: one catastrophic residual widens its own standard error, so z alone would keep
#: it (frames 0-2 of the validation set: -0.01 / 0.00 dB from 1 / 4 spp, and it removed 20-700x bright
#: pixels from mi_glass_mirror, while the op centred values at their range's middle; since they are
#: centred nearest 0, without it 0.000 / -0.008, `bl_moving_metal` -0.07 from 4 spp)
_SELECTION_ERROR_CUT = 2.0


#: levels fewer in the tree of each frame's own candidates than in the window's at the same bandwidth: a
#: narrow kernel's filter is the costliest (its grid is the finest), and the validation set measured alike
#: with one level fewer (the default's 2 px candidate: -0.005 / +0.003 dB from 1 / 4 spp, colour alone
#: +0.003 / +0.006; two fewer -0.015 / -0.025) for a third of its time (19.5 -> 6.5 ms a 256x256 frame, one
#: thread)
_FRAME_ALONE_FEWER_LEVELS = 1


#: z^2 of a bandwidth left out (weight exp(-z^2 / 2) = 0)
_LEFT_OUT = 1e30


#: Cross-validation takes each pixel's noise as its own. A reconstruction filter that splats each sample
#: into the pixels around (Mitsuba's default, a gaussian of 2 px radius) shares samples between
#: neighbours: the other half's prediction then holds part of the pixel's own noise and narrow
#: bandwidths look right. A bounce-lit room rendered so (mi_indirect_dof, gaussian) came out 2 dB under a
#: plain Gaussian blur from 1 spp. Where the noise is found correlated (:func:`_cv_cell`) the halves are a
#: checkerboard of squares this many pixels wide, so that most pixels (36 of 64) have no neighbour in the
#: other half. On six Mitsuba clips rendered so, 8 px scored best on four and within 0.06 dB of 4 px on the
#: fifth (that room: 2 / 4 / 8 px +1.3 / +3.7 / +5.0 dB); 8 px squares everywhere would cost the 12
#: box-filtered scenes 0.05 / 0.11 dB from 1 / 4 spp, at most 0.35 on one (benchmarks/validation/findings.md),
#: so they are only where the test finds them needed.
_CORRELATED_CELL = 8


#: the test: in rows (and columns) of four pixels on one plain surface, how often the differences of the
#: two adjacent pairs, x1 - x0 and x2 - x3, have one sign. Their covariance is the correlation of adjacent
#: pixels (less twice that of pixels two apart, and a plain surface's slope), so independent noise gives
#: them one sign half the time and splatted samples more often: 0.47-0.52 on every frame of the validation
#: clips that has the pairs (and of two Cycles clips with its Blackman-Harris filter), 0.557-0.63 on five
#: Mitsuba clips rendered with its gaussian (benchmarks/validation/findings.md); the bound lies between.
#: A frame with too few pairs on plain surfaces (texture everywhere) takes the residual's share (below)
#: against this bound: every frame of the set, its probes and its clips at 256x256 stays under it (the fog
#: probe's residual reads up to 0.527 from 1 spp), `mi_still_textures` rendered with Mitsuba's gaussian
#: reads 0.568-0.601
_CORRELATED_SIGNS = 0.535


#: a plain surface: albedo and normal within a quarter of their range sigmas over the four pixels
_PLAIN_SPAN = 0.25


#: the feature groups constant over a plain surface (depth and position run along it)
_PLAIN_GROUPS = ("albedo", "N", "Ncam")


#: pairs of differences the share needs (a frame with fewer says nothing): its standard error is then at
#: most 0.011, and the bound three of them above one half
_MIN_SIGN_PAIRS = 2000


#: Without albedo nothing marks a plain surface (normals alone take in texture, which pulls the share below
#: one half), so the test runs on every row of four pixels of the colour's residual about its own Gaussian
#: blur of this width (pixels): the blur takes out most of the texture and shading, and its taps give
#: independent noise a share a little under one half.
_RESIDUAL_BLUR = 1.0


#: the bound on the residuals' share: first frames of the validation clips from 1 and 4 spp 0.47-0.51, the
#: two Cycles clips with its Blackman-Harris filter 0.45-0.49, the six Mitsuba clips with its gaussian
#: 0.543-0.589 (benchmarks/validation/findings.md); the bound lies between
_CORRELATED_RESIDUAL_SIGNS = 0.525


#: the squares there: without albedo only the narrow candidates keep texture, and inside a square they have
#: no sample of the other half within reach, so they go unjudged. The six Mitsuba clips with its gaussian,
#: colour alone, from 1 / 4 spp: squares of 2 / 4 / 8 px 23.57 / 26.82, 24.25 / 27.00, 24.25 / 26.33 dB
#: (per-pixel halves 22.64 / 25.94); 8 px blurs `mi_still_textures` 2.5 dB under its raw frames from 4 spp,
#: 4 px leaves the bounce-lit room 3 / 2 dB under a Gaussian blur (7 with per-pixel halves)
_CORRELATED_CELL_NO_ALBEDO = 4


def _cv_cell(e: Tensor, valid: Tensor, features: Tensor, sigmas: Tensor) -> Tensor:
    """Each frame's cross-validation cell ``(T,)`` int64: :data:`_CORRELATED_CELL` where neighbouring pixels'
    noise is correlated, else 1. From the samples ``e`` ``(T, 3, H, W)`` at ``valid`` pixels (bool
    ``(T, 1, H, W)``) and the guide's albedo and normal channels ``(T, F, H, W)`` of range sigmas ``(T, F)``:
    in every row (column) of four valid pixels on one plain surface, whether ``x1 - x0`` and ``x2 - x3`` have
    one sign (a difference of 0, as between two black pixels, tells nothing). With no such channel (``F`` 0:
    no albedo guides), in every row of four valid pixels of the residual about a blur
    (:data:`_RESIDUAL_BLUR`, :data:`_CORRELATED_RESIDUAL_SIGNS`), and the squares are
    :data:`_CORRELATED_CELL_NO_ALBEDO` wide. A frame with too few pairs on plain surfaces (texture
    everywhere) is tested on the residual too, against its own bound (:data:`_CORRELATED_SIGNS`)."""
    with torch.no_grad():
        T = e.shape[0]
        x = luminance(torch.where(valid, e, 0.0))
        if features.shape[1] == 0:
            agree, total = _sign_pairs(x - footprint_blur(x, _RESIDUAL_BLUR), valid)
            correlated = (total >= _MIN_SIGN_PAIRS) & (agree > _CORRELATED_RESIDUAL_SIGNS * total)
            return torch.where(correlated, _CORRELATED_CELL_NO_ALBEDO, torch.ones(T, dtype=torch.int64))
        plain_guide = features / sigmas.to(features.dtype).clamp_min(1e-30)[:, :, None, None]
        agree, total = _sign_pairs(x, valid, plain_guide)
        few = total < _MIN_SIGN_PAIRS
        if bool(few.any()):
            ids = few.nonzero()[:, 0]
            agree[ids], total[ids] = _sign_pairs(x[ids] - footprint_blur(x[ids], _RESIDUAL_BLUR), valid[ids])
        correlated = (total >= _MIN_SIGN_PAIRS) & (agree > _CORRELATED_SIGNS * total)
        return torch.where(correlated, _CORRELATED_CELL, torch.ones(T, dtype=torch.int64))


def _sign_pairs(x: Tensor, valid: Tensor, plain_guide: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Per frame, of the rows and columns of four valid pixels of ``x`` ``(T, 1, H, W)`` (on one plain surface
    of ``plain_guide`` ``(T, F, H, W)``, in units of its range sigmas, where given), how many have ``x1 - x0``
    and ``x2 - x3`` of one sign, and how many have both nonzero: ``(T,)`` int64 each (:func:`_cv_cell`)."""
    T = x.shape[0]
    agree, total = torch.zeros(T, dtype=torch.int64), torch.zeros(T, dtype=torch.int64)
    for dim in (-1, -2):
        n = x.shape[dim] - 3
        if n <= 0:
            continue
        at = [x.narrow(dim, k, n) for k in range(4)]
        near, far = torch.sign(at[1] - at[0]), torch.sign(at[2] - at[3])
        if plain_guide is None:
            plain = torch.ones_like(near, dtype=torch.bool)
        else:
            four = [plain_guide.narrow(dim, k, n) for k in range(4)]
            hi = torch.maximum(torch.maximum(four[0], four[1]), torch.maximum(four[2], four[3]))
            lo = torch.minimum(torch.minimum(four[0], four[1]), torch.minimum(four[2], four[3]))
            plain = (hi - lo).amax(1, keepdim=True) < _PLAIN_SPAN
        for k in range(4):
            plain &= valid.narrow(dim, k, n)
        counted = plain & (near != 0) & (far != 0)
        agree += (counted & (near == far)).flatten(1).sum(1)
        total += counted.flatten(1).sum(1)
    return agree, total


#: Caustic light (our tracer's ``caustic`` feature: the share of a sample's light that came from a light
#: through mirrors or glass after a diffuse vertex) is too sparse for the cross-validation to see a wide
#: bandwidth's bias: at 10 spp the caustic under the built-in scene's glass ball is lit by one to three
#: samples a pixel, and the blend took the wide candidates there. Where the share, pooled under a Gaussian of
#: ``_CAUSTIC_POOL`` pixels, reaches the first of ``_CAUSTIC_SHARES``, the narrowest candidate takes over,
#: wholly from the second, as far as the caustic is narrower than the pool (:func:`_caustic_light`). Set on
#: the progressive loop over loop seeds (benchmarks/validation/findings.md): after 10 iterations caustic
#: energy 0.853 -> 0.900 at 96x96 (4 frames, 32 seeds), 0.827 -> 0.888 at 128x128, after 16 on the render
#: job's 256x256 with 8 frames 0.918 -> 0.948, +0.02 / +0.01 / +0.01 dB, no iteration of 1-16 worse; without
#: the test of width, -0.04 / -0.05 dB at 256x256 after 10 / 16 (the narrowest candidate inside a caustic
#: wider than it), and with shares of (0, 0.05) as well -0.01 / -0.02 dB at 96x96 / 128x128 (the speckle that
#: mirrors and glass scatter over the walls)
_CAUSTIC_POOL = 3.0
_CAUSTIC_SHARES = (0.01, 0.04)


def _caustic_light(features: Tensor, names: Sequence[str], mask: Tensor) -> Tensor | None:
    """The narrowest candidate's weight for caustic light, ``(T, 1, H, W)`` in [0, 1]: the ``caustic``
    feature's share pooled over the finite samples (``mask`` ``(T, 1, H, W)`` above 0), ramped between
    :data:`_CAUSTIC_SHARES`, where it stands above its own mean over the pool (a caustic narrower than the
    pool); ``None`` where ``names`` hold no ``caustic`` channel."""
    k = [i for i, n in enumerate(names) if feature_table.group_of(n) == "caustic"]
    if not k:
        return None
    share = torch.nan_to_num(features[:, k[0]:k[0] + 1], 0.0, 0.0, 0.0).clamp(0.0, 1.0)
    valid = (mask > 0).to(share.dtype)
    lo, hi = _CAUSTIC_SHARES
    w = ((_normalised_blur(share, valid, _CAUSTIC_POOL) - lo) / (hi - lo)).clamp(0.0, 1.0)
    # a wide kernel's bias lies where the caustic is narrower than the kernel: there the weight stands above
    # its own mean over the pool, and the excess (doubled, at most the weight) is what it keeps; inside a
    # caustic wider than the pool (all light through a window, say) the wide candidates average caustic light
    # with caustic light
    return (2.0 * (w - _normalised_blur(w, valid, _CAUSTIC_POOL))).clamp_min(0.0).minimum(w)


def _narrowest_where(out: Tensor, candidates: "_Candidates", bandwidths: Sequence[float],
                     weight: Tensor | None) -> Tensor:
    """The blend ``out`` ``(Q, 3, H, W)`` moved toward the candidate of the narrowest of ``bandwidths`` (the
    window's) by ``weight`` ``(Q, 1, H, W)`` (:func:`_caustic_light` at the queries); ``out`` where it is
    0."""
    if weight is None or not bool((weight > 0).any()):
        return out
    narrowest = candidates.fulls[min(range(len(bandwidths)), key=lambda k: float(bandwidths[k]))]
    weight = weight.to(out.dtype)
    return torch.where(weight > 0, torch.lerp(out, narrowest, weight), out)


def _select_bandwidth(e: Tensor, mask: Tensor, guide: Tensor, sigmas: Tensor,
                      settings: DenoiseSettings, ft: list[float], qt: list[float], sigma_s: float,
                      range_scale: float, level: Tensor | None, pooling: Tensor | None = None,
                      cell: int = 1, caustic: Tensor | None = None) -> Tensor:
    """Filter ``e`` at every bandwidth of ``settings.bandwidths`` (and each query's frame alone at those of
    ``settings.frame_alone``) and blend them per pixel by their error.

    The error of a bandwidth at a pixel is estimated by cross-validation on two interleaved halves of
    the pixels (Rousselle et al. 2012): each sample is predicted by the filter of the other half's
    samples alone, whose noise is independent of it, so the squared difference is the prediction's
    error plus the sample's variance, the same for every bandwidth. The squared differences are
    weighted as relative errors (against ``level``, a radiance estimate, plus a tenth of the frame's
    mean) and pooled over ``selection_blur`` pixels; a bandwidth's weight is the likelihood that its
    excess over the least error is noise (:func:`_excess_error_z2`). Each bandwidth's own output uses
    all samples (the two halves' sums add up).

    Args:
        e: ``(T, 3, H, W)`` samples; mask ``(T, 1, H, W)`` their weights (0: not filtered here).
        level: ``(T, 3, H, W)`` radiance estimate at the frames, or ``None`` (then the output at
            ``sigma_s`` itself).
        pooling: ``(T,)`` the factor on ``selection_blur`` at each frame (``FrameState.pooling``), or
            ``None`` (1).
        cell: the halves' checkerboard squares, in pixels (:func:`_cv_cell`).
        caustic: ``(Q, 1, H, W)`` the narrowest bandwidth's weight at the queries where caustic light lands
            (:func:`_caustic_light`), or ``None``.

    Returns:
        ``(Q, 3, H, W)`` at the query times.
    """
    candidates = _bandwidth_candidates(e, mask, guide, sigmas, settings, ft, qt, sigma_s, range_scale, level,
                                       pooling, cell)
    return _narrowest_where(candidates.blend(settings.selection_softness), candidates, settings.bandwidths,
                            caustic)


@dataclass
class _Candidates:
    """:func:`_select_bandwidth` before its blend: the K bandwidths' outputs ``fulls`` (each ``(Q, 3, H, W)``)
    at the queries, and how to weigh them. Where every query is a frame (``z2`` ``None``): each query's
    predictions of its samples from the other half ``preds``, the samples ``e`` (in the window's brightness
    unit), their relative ``weight`` and ``mask`` (``(Q, 3 | 1, H, W)``), and each query's pooling width
    ``blurs``; otherwise the z^2 of every candidate, interpolated to the queries."""

    fulls: list
    preds: list | None = None
    e: Tensor | None = None
    weight: Tensor | None = None
    mask: Tensor | None = None
    blurs: list | None = None
    z2: Tensor | None = None
    units: Tensor | None = None

    def query(self, i: int) -> "_Candidates":
        """The candidates of query ``i`` alone (at frames)."""
        one = slice(i, i + 1)
        return _Candidates([f[one] for f in self.fulls], [p[one] for p in self.preds], self.e[one],
                           self.weight[one], self.mask[one], self.blurs[i:i + 1], units=self.units[one])

    @staticmethod
    def cat(cs: "list[_Candidates]") -> "_Candidates":
        """Queries' candidates (at frames) as one."""
        def join(xs):
            return [torch.cat(x) for x in zip(*xs)]
        if len(cs) == 1:
            return cs[0]
        return _Candidates(join([c.fulls for c in cs]), join([c.preds for c in cs]),
                           *(torch.cat([getattr(c, n) for c in cs]) for n in ("e", "weight", "mask")),
                           [b for c in cs for b in c.blurs], units=torch.cat([c.units for c in cs]))

    def residuals(self) -> Tensor:
        """The residual planes its neighbours' blends borrow (at frames): ``(K + 1, Q, 1, H, W)``, each
        candidate's weighted squared residuals (:func:`_residual_planes`), then the mask. They are relative
        errors times the square of ``units`` (float64 ``(Q,)``: each query's level unit over its window's
        brightness unit, which differ from query to query)."""
        return _residual_planes(self.preds, self.e, self.weight, self.mask)

    def blend(self, softness: float, others: Tensor | None = None,
              other_weights: Tensor | None = None) -> Tensor:
        """The candidates blended per pixel, ``(Q, 3, H, W)``. ``others`` ``(J, K + 1, Q, 1, H, W)``: the
        residual planes of J neighbouring queries, pooled with each query's own under ``other_weights``
        ``(J, Q, 1, H, W)`` (:func:`_excess_error_z2`)."""
        if self.z2 is not None:
            return _blend(self.fulls, self.z2, softness)
        own = [self.e, self.weight, self.mask]
        if not (softness > 0 and self.blurs[0] > 0 and _fast.enabled(*own, *self.preds, *self.fulls)):
            z2 = _z2_by_width(self.preds, *own, self.blurs, others, other_weights)
            return _blend(self.fulls, z2, softness)
        outs = []
        for g in _width_groups(self.blurs):
            o, w = _lenders_part(others, other_weights, g)
            if o is not None:
                o, w = o[:, :, :, 0], w[:, :, 0]
            preds, fulls = _frames_of(self.preds, g), _frames_of(self.fulls, g)
            outs.append(_fast.cv_blend(preds, fulls, *_frames_of(own, g), self.blurs[g[0]], softness,
                                       _SELECTION_ERROR_CUT, o, w))
        return torch.cat(outs)


def _width_groups(blurs: list) -> list[list[int]]:
    """The queries that pool over one width, which go in one call (frames pool apart)."""
    return [list(range(len(blurs)))] if len(set(blurs)) == 1 else [[i] for i in range(len(blurs))]


def _frames_of(xs: list, g: list) -> list:
    """Each of ``xs`` at the queries ``g`` (views: a group is a run of queries)."""
    return [_frames(x, g) for x in xs]


def _lenders_part(others: Tensor | None, other_weights: Tensor | None, g: list) -> tuple:
    """The neighbours' residual planes ``(J, K + 1, Q, ...)`` and weights ``(J, Q, ...)`` at the queries
    ``g``."""
    if others is None:
        return None, None
    return others[:, :, g[0]:g[-1] + 1], other_weights[:, g[0]:g[-1] + 1]


def _z2_by_width(preds: list, e: Tensor, weight: Tensor, mask: Tensor, blurs: list,
                 others: Tensor | None = None, other_weights: Tensor | None = None) -> Tensor:
    """:func:`_candidate_z2` of the queries, each group of one pooling width (``blurs``) in one call:
    ``(K, Q, 1, H, W)``."""
    return torch.cat([_candidate_z2(_frames_of(preds, g), *_frames_of([e, weight, mask], g), blurs[g[0]],
                                    *_lenders_part(others, other_weights, g))
                      for g in _width_groups(blurs)], 1)


#: how far apart two queries' residual units may lie for one to lend the other its residuals (a factor; a
#: guard against float32 overflow and a black frame beside lit ones, not a tuned figure)
_UNITS_APART = 1e-6


class ClipCache:
    """What a clip's calls share: the bandwidth candidates of each query they have filtered, so that a query's
    candidates serve its own blend and its neighbours' evidence (:func:`_pooled_selection`) and are filtered
    once, and the flows between its frames (:class:`~torchmanifold.pipeline.align.WindowAlignment`). An entry
    comes from its query's window (or its two frames) alone, so it holds the same bytes whichever call made
    it; the caller keeps one cache per clip and settings. Calls on several threads share it: an entry another
    thread is making is waited for."""

    def __init__(self):
        self._lock = threading.Lock()
        self._entries: dict = {}

    def get(self, keys: list, compute) -> list:
        """The entries of ``keys``; those no call has made yet come from ``compute(missing keys)`` (a list of
        entries), made here. An entry released meanwhile (:meth:`release_before`) is still returned."""
        with self._lock:
            futures, mine = {}, []
            for k in keys:
                if k not in self._entries:
                    self._entries[k] = Future()
                    mine.append(k)
                futures[k] = self._entries[k]
        if mine:
            try:
                for k, v in zip(mine, compute(mine)):
                    futures[k].set_result(v)
            except BaseException as err:
                with self._lock:
                    for k in mine:
                        if self._entries.get(k) is futures[k]:
                            del self._entries[k]
                        futures[k].set_exception(err)
                raise
        return [futures[k].result() for k in keys]

    def release_before(self, time: float) -> None:
        """Forget the entries of queries before ``time`` (a streamed clip's windows have moved past them)."""
        with self._lock:
            for k in [k for k in self._entries if k[0] < time]:
                del self._entries[k]


def _pooled_selection(e: Tensor, mask: Tensor, guide: Tensor, sigmas: Tensor, settings: DenoiseSettings,
                      ft: list[float], qt: list[float], sigma_s: float, range_scale: float,
                      level: Tensor | None, pooling: Tensor | None, cell: int, neighbours: list[list[int]],
                      cache: ClipCache | None, align: WindowAlignment | None = None,
                      caustic: Tensor | None = None) -> Tensor:
    """:func:`_select_bandwidth` at queries that are frames, each blending with its neighbouring frames'
    cross-validated residuals as evidence (``neighbours``: per query, the frame indices whose queries lend
    theirs). A neighbour's residuals weigh ``exp(-d^2 / 2)`` at a pixel, ``d`` the distance of its guide there
    from the query's in range sigmas: where the same surface under the same light shows, a candidate's bias
    is the same and the noise independent. With ``align``, each query filters its window brought to its own
    pixels, and a neighbour's residuals and guide are brought to the query's pixels. ``caustic`` as there."""
    idx = [frame_at(ft, q) for q in qt]
    need = sorted(set(idx) | {n for ns in neighbours for n in ns})
    # an entry's key: the frames its window holds in this call's state (a call whose state cuts a neighbour's
    # window short makes its own entry) and what another call's state may set otherwise (a noisy pilot's
    # window drops each frame's own candidates; a query between frames leaves the windows as they are)
    key = (settings.temporal_radius, settings.frame_alone, float(sigma_s), float(range_scale), cell,
           align is not None)

    def lent(c: _Candidates) -> list:
        planes = c.residuals()
        return [_Lent(c.query(i), planes[:, i:i + 1], c.units[i]) for i in range(planes.shape[1])]

    def frames_read(times: list) -> slice:
        # the frames the queries' filters read (as a view: frames between two queries' windows come along, and
        # no query's bytes depend on them); all where a query lies between frames (its errors come from the
        # frames around it, each cross-validated over its own window)
        if any(frame_at(ft, t) is None for t in times):
            return slice(0, len(ft))
        r = windows_span(ft, times, settings.temporal_radius)
        return slice(r.start, r.stop)

    def compute(times: list) -> list:
        if align is None or not any(align.moves(frame_at(ft, t)) for t in times):
            r = frames_read(times)
            return lent(_bandwidth_candidates(e[r], mask[r], guide[r], sigmas[r], settings, ft[r], times,
                                              sigma_s, range_scale, None if level is None else level[r],
                                              None if pooling is None else pooling[r], cell))
        out = []
        for t in times:  # each query's window at its own pixels
            k, r = frame_at(ft, t), frames_read([t])

            def moved(x: Tensor, weights: bool = False) -> Tensor:
                return align.frames(x, k, weights, range(r.start, r.stop))
            out += lent(_bandwidth_candidates(moved(e), moved(mask, True), moved(guide), sigmas[r], settings,
                                              ft[r], [t], sigma_s, range_scale,
                                              None if level is None else moved(level),
                                              None if pooling is None else pooling[r], cell))
        return out

    keys = [(ft[k], tuple(ft[j] for j in window(ft, ft[k], settings.temporal_radius)), *key) for k in need]
    got = dict(zip(need, (cache.get(keys, lambda ks: compute([k[0] for k in ks])) if cache is not None
                          else compute([ft[k] for k in need]))))
    # a query's own candidates, made again where the cache kept only what it lends (a query asked twice)
    again = [k for k in idx if got[k].candidates is None]
    if again:
        for k, lent in zip(again, compute([ft[k] for k in again])):
            got[k] = lent
    cands = _Candidates.cat([got[k].candidates for k in idx])
    if cache is not None:  # what a cache holds of a blended query is what it lends its neighbours
        for k in idx:
            got[k].candidates = None
    J = max((len(ns) for ns in neighbours), default=0)
    if J == 0:
        return _narrowest_where(cands.blend(settings.selection_softness), cands, settings.bandwidths, caustic)
    planes = got[idx[0]].residuals
    others = planes.new_zeros((J, planes.shape[0], len(qt), 1, *guide.shape[2:]))
    weights = planes.new_zeros((J, len(qt), 1, *guide.shape[2:]))
    for i, (k, ns) in enumerate(zip(idx, neighbours)):
        ranges = (sigmas[k] * range_scale).to(guide.dtype).clamp_min(1e-30)[:, None, None]  # the query's
        for j, n in enumerate(ns):
            # in the query's units; a neighbour whose units lie orders of magnitude away (a black frame
            # beside lit ones) lends nothing
            factor = float((cands.units[i] / got[n].units) ** 2)
            if not _UNITS_APART < factor < 1.0 / _UNITS_APART:
                continue
            theirs = got[n].residuals if align is None else align.frame(got[n].residuals, k, n)
            others[j, :-1, i] = theirs[:-1, 0] * factor
            others[j, -1, i] = theirs[-1, 0]
            their_guide = guide[n] if align is None else align.frame(guide[n], k, n)
            weights[j, i, 0] = torch.exp(-0.5 * (((their_guide - guide[k]) / ranges) ** 2).sum(0))
            if align is not None and align.flow(k, n) is not None:  # no evidence from outside their frame
                weights[j, i, 0] *= align.flow(k, n).inside
    blend = cands.blend(settings.selection_softness, others, weights)
    return _narrowest_where(blend, cands, settings.bandwidths, caustic)


class _Lent:
    """A query's entry in a :class:`ClipCache`: its bandwidth candidates until its own blend is done,
    and what it lends its neighbours' blends, its residual planes ``(K + 1, 1, 1, H, W)`` and their units."""

    __slots__ = ("candidates", "residuals", "units")

    def __init__(self, candidates: _Candidates | None, residuals: Tensor, units: Tensor):
        self.candidates, self.residuals, self.units = candidates, residuals, units


def _bandwidth_candidates(e: Tensor, mask: Tensor, guide: Tensor, sigmas: Tensor,
                          settings: DenoiseSettings, ft: list[float], qt: list[float], sigma_s: float,
                          range_scale: float, level: Tensor | None, pooling: Tensor | None = None,
                          cell: int = 1) -> _Candidates:
    """:func:`_select_bandwidth`'s filters and cross-validation, the blend left to do (arguments as there)."""
    T = e.shape[0]
    st = settings
    # Where every query is a frame, cross-validate at the queries alone (a query's window is filtered
    # once, its halves' sums are its output); otherwise at every frame, the errors interpolated.
    query_frames = [frame_at(ft, q) for q in qt]
    at_frames = all(k is not None for k in query_frames)
    cv_times = qt if at_frames else ft
    idx = query_frames if at_frames else list(range(T))
    preds, fulls, cv_outs = [], [], []
    stack = _halves_stack(e, mask, cell)
    # the window's bandwidths, then those of each frame alone (levels fewer)
    groups = [(st, st.bandwidths, 0)]
    if st.frame_alone:
        groups.append((replace(st, temporal_radius=0), st.frame_alone, _FRAME_ALONE_FEWER_LEVELS))
    for s, bandwidths, fewer in groups:
        filters = [_Filter(guide, sigmas, s, ft, cv_times, sigma_s * float(b), range_scale,
                           max(1, tree_height_at(s, b) - fewer)) for b in bandwidths]
        # the guard's window bounds hold for every bandwidth (per-frame queries bound inside the fused kernel)
        windowed = not filters[0]._per_frame() and e.dtype != torch.float64
        bounds = filters[0].window_bounds(e, mask) if windowed else None
        for b, filt, y in zip(bandwidths, filters, _Filter.apply_each(filters, stack)):
            pred, num, den = _split_halves(y, cell)
            cv_out = filt.normalise(num, den, e, mask, bounds)
            preds.append(pred)
            cv_outs.append(cv_out)
            if at_frames:
                fulls.append(cv_out)
            else:
                at_queries = _Filter(guide, sigmas, s, ft, qt, sigma_s * float(b), range_scale,
                                     filt.tree_height)
                fulls.append(at_queries(e, mask))
    if level is None:
        level = cv_outs[min(range(len(st.bandwidths)), key=lambda k: abs(math.log(st.bandwidths[k])))]
    else:
        level = _frames(level, idx)
    # the residuals in units of the brightest frame mean of each query's window (its prediction mixes the
    # window's frames), so that the z statistics, which square their squares, overflow float32 neither on
    # a clip of values about 1e10 nor on a black frame between lit ones; per window, not per call, so that
    # a frame's bytes do not depend on which other frames share the call (a unit: no gradient passes it)
    brightness = _frame_mean(luminance(e.detach()).clamp_min(0.0), mask)[:, 0, 0, 0]
    top = torch.stack([brightness[window(ft, t, st.temporal_radius)].amax() for t in cv_times]).view(-1, 1, 1, 1)
    scale = torch.where(top > 0, top, torch.ones_like(top))
    e, mask = _frames(e, idx), _frames(mask, idx)
    e = _own_half_reference(e, mask, _frames(guide, idx), (sigmas[idx] * range_scale).to(guide.dtype), cell,
                            _REFERENCE_WIDTH * sigma_s)
    weight, unit = _relative_weight(level, mask)
    e, preds = e / scale, [p / scale for p in preds]
    # each frame pools over its own width, widened at most to the widest candidate's (a candidate's bias
    # varies on its own scale: pooling wider mixes places where it differs)
    widest = sigma_s * max(st.bandwidths)
    blurs = [st.selection_blur if pooling is None else
             max(st.selection_blur, min(st.selection_blur * float(pooling[k]), widest)) for k in idx]
    if at_frames:
        # a unit, as scale is: no gradient passes it
        units = (unit.detach().double() / scale.double()).view(-1)
        return _Candidates(fulls, preds, e, weight, mask, blurs, units=units)
    z2 = _z2_by_width(preds, e, weight, mask, blurs)
    return _Candidates(fulls, z2=torch.stack([_Filter.at_frames_to_queries(x, ft, qt) for x in z2]))


#: the spatial sigma of :func:`_own_half_reference`, as a share of the bandwidths' unit ``sigma_s`` (1 px
#: from 1 spp, where the unit is 4 px; it shrinks with the unit as the samples grow, and the progressive
#: loop's late iterations measure against their samples alone). Against each sample alone, from 1 / 4 spp:
#: the set (twelve clips, all frames) +0.011 / +0.015 dB, its six Mitsuba clips at 256x256 +0.013 / +0.013,
#: four Cycles clips at 256x256 +0.019 / +0.016, the fifteen 128x128 probes +0.028 / +0.022, the two sunlit
#: rooms +0.12 / +0.04, no clip below -0.01; 0.2 / 0.375 gave the rooms +0.09 / +0.14 and +0.04 / +0.01, the
#: set +0.013 / +0.018 and +0.003 / +0.014 (``benchmarks/validation/findings.md``)
_REFERENCE_WIDTH = 0.25


def _own_half_reference(e: Tensor, mask: Tensor, guide: Tensor, ranges: Tensor, cell: int,
                        sigma: float) -> Tensor:
    """What each sample's cross-validation residuals are measured against, ``(T, 3, H, W)``: the sample
    ``e`` ``(T, 3, H, W)`` averaged with those of its 3x3 neighbours in its own checkerboard half (squares of
    ``cell`` pixels; the four diagonal ones for single pixels), weighted by ``mask`` ``(T, 1, H, W)``, a
    Gaussian of ``sigma`` pixels and the range kernel of ``guide`` ``(T, D, H, W)`` in ``ranges`` ``(T, D)``.

    A prediction from the other half is independent of the whole own half, so the residuals keep their
    expectation but for the average's bias, which a 3x3 kernel of a surface's own samples keeps small; their
    noise, a single sample's at 1 spp, shrinks by up to half, and with it the noise of every candidate's
    pooled error. ``e`` itself where no weight lies under the kernel."""
    if sigma <= 0:
        return e
    H, W = e.shape[-2:]
    r = ranges.clamp_min(1e-30)[:, :, None, None]
    half = _halves(e.shape, e.device, cell)

    def padded(x: Tensor) -> Tensor:
        return torch.nn.functional.pad(x, (1, 1, 1, 1))
    ep, mp, gp = padded(e * mask), padded(mask), padded(guide)
    own = half.to(torch.int8)
    hp = torch.nn.functional.pad(own, (1, 1, 1, 1), value=-1)
    num, den = e * mask, mask
    for dy, dx in [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]:
        at = (..., slice(1 + dy, 1 + dy + H), slice(1 + dx, 1 + dx + W))  # the neighbour at (dy, dx)
        same = hp[at] == own
        if not bool(same.any()):  # the other half everywhere (a single pixel's four adjacent ones)
            continue
        w = math.exp(-(dy * dy + dx * dx) / (2 * sigma * sigma)) * same.to(e.dtype) * mp[at] \
            * torch.exp(-0.5 * (((gp[at] - guide) / r) ** 2).sum(1, keepdim=True))
        num, den = num + w * ep[at], den + w
    return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), e)


def _relative_weight(level: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """The weight of each pixel's squared residuals, ``(T, 1, H, W)``, as a relative error against ``level``
    ``(T, 3, H, W)``'s luminance plus :data:`~torchmanifold.pipeline.image._LOG_RADIANCE_OFFSET` of the
    frame's mean over ``mask`` (``(T, 1, H, W)``, which it multiplies), and that mean, ``(T, 1, 1, 1)`` (1
    where it is 0)."""
    lum = luminance(level).clamp_min(0.0)
    mean = _frame_mean(lum, mask)
    # relative errors, in units of the frame's mean: a per-frame factor leaves every z unchanged, and
    # the weights stay at most 1 / offset^2 on a frame whose mean is tiny or 0 (a black frame)
    unit = torch.where(mean > 0, mean, torch.ones_like(mean))
    return mask / (lum / unit + _LOG_RADIANCE_OFFSET) ** 2, unit


def _blend(fulls: list, z2: Tensor, softness: float) -> Tensor:
    """The candidates ``fulls`` (each ``(T, 3, H, W)``) blended per pixel by their ``z2`` ``(K, T, 1, H,
    W)``: weights ``exp(-z^2 / (2 softness^2))`` normalised, or the least error alone for ``softness`` 0."""
    if softness > 0:
        w = torch.softmax(-z2 / (2 * softness ** 2), 0)
    else:  # the least error has z = 0
        w = torch.nn.functional.one_hot(z2.argmin(0)[:, :, 0], len(z2)).permute(3, 0, 1, 2)[:, :, None]
        w = w.to(fulls[0].dtype)
    return (torch.stack(fulls) * w).sum(0)


#: the widths flat pixels choose among, as multiples of the flat average's width (factor-2 steps):
#: 0.25 reaches the samples themselves (0.5 px from 1 spp), 2 a smooth reflection's width. Set on the
#: ``mi_glass_room`` probe (256x256: ``mi_ceiling_light``'s room with a glass ball, a glass pane and a
#: mirror), from 1 / 4 spp against the plain flat average: (0.5, 1, 2) +0.30 / +0.39 dB, (0.25, 0.5, 1)
#: +0.38 / +0.32, these four +0.33 / +0.47 (``benchmarks/validation/findings.md``)
_FLAT_WIDTHS = (0.25, 0.5, 1.0, 2.0)


def _select_flat_width(e: Tensor, weight: Tensor, sigma: float, cell: int, blur: float, softness: float,
                       guided: Callable[[Tensor, list[float]], list[Tensor]] | None = None,
                       at: Sequence[int] | None = None) -> Tensor:
    """Flat pixels' average at the frames ``at`` (default all), ``(len(at), 3, H, W)``: filters of
    :data:`_FLAT_WIDTHS` times ``sigma`` pixels over the samples ``e`` ``(T, 3, H, W)`` of nonzero ``weight``
    ``(T, 1, H, W)``, blended per pixel as :func:`_select_bandwidth` blends its bandwidths: each checkerboard
    half (squares of ``cell`` pixels) is predicted from the other's samples at each width, the residuals
    relative to the average at ``sigma`` are pooled over ``blur`` pixels and a width weighs
    ``exp(-z^2 / (2 softness^2))`` (``softness`` 0: the least error alone). What glass or a mirror shows is
    sharp detail in one place (a refracted checkerboard, 1 px wanted) and smooth light in another (a
    reflected wall, 4 px): one width for all loses either.

    The filters are Gaussians of each frame alone, or ``guided(stack, widths)``: the filter of the halves'
    stack (:func:`~torchmanifold.pipeline.filter._halves_stack` of all ``T`` frames) at each width, a
    ``(len(at), 8, H, W)`` tensor each (the denoiser's: guided by the samples' colour and joined in time,
    :func:`~torchmanifold.pipeline.denoise._flat_filters`). ``e`` itself where no weight lies under the
    kernel."""
    at = list(range(e.shape[0])) if at is None else list(at)
    widths = [sigma * f for f in _FLAT_WIDTHS]
    if guided is None:  # a Gaussian of both halves' sums: each half's prediction of the other, and both
        stack, ones = _halves_stack(e[at], weight[at], cell), torch.ones_like(weight[at])
        filtered = [_normalised_blur(stack, ones, w) for w in widths]
    else:
        filtered = guided(_halves_stack(e, weight, cell), widths)
    e, m = e[at], (weight[at] > 0).to(e.dtype)
    preds, fulls = [], []
    for y in filtered:
        pred, num, den = _split_halves(y, cell)
        preds.append(pred)
        fulls.append(torch.where(den > 1e-8, num / den.clamp_min(1e-8), e))
    rel, unit = _relative_weight(fulls[_FLAT_WIDTHS.index(1.0)], m)
    unit = unit.detach()  # a unit: no gradient passes it (nor a prediction's NaN where it has no support)
    e, preds = e / unit, [p / unit for p in preds]  # in frame units: z^2 squares squares
    if softness > 0 and blur > 0 and _fast.enabled(e, rel, m, *preds, *fulls):
        return _fast.cv_blend(preds, fulls, e, rel, m, blur, softness, _SELECTION_ERROR_CUT)
    return _blend(fulls, _candidate_z2(preds, e, rel, m, blur), softness)


def _residual_planes(preds: list, e: Tensor, weight: Tensor, mask: Tensor) -> Tensor:
    """Each candidate's squared cross-validation residuals ``(K + 1, T, 1, H, W)`` from its predictions
    ``preds`` of the samples ``e`` ``(T, 3, H, W)``, weighted by ``weight`` ``(T, 1, H, W)``, then
    ``mask``."""
    if _fast.enabled(e, weight, mask, *preds):
        return _fast.cv_residuals(preds, e, weight, mask)[:, :, None]
    return torch.cat([_squared_residuals(preds, e, weight)[0], mask[None]])


def _squared_residuals(preds: list, e: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
    """``(K, T, 1, H, W)`` weighted squared residuals of ``preds`` against ``e``, and where each prediction
    held (bool, like them). A prediction with no sample of the other half under its kernel (NaN) tells
    nothing of its error: it pools as the worst candidate's residual there (its residual is taken as 0 first,
    so no NaN reaches a gradient)."""
    held = torch.stack([~torch.isnan(p).any(1, keepdim=True) for p in preds])  # (K, T, 1, H, W)
    sq = torch.stack([(torch.where(h, p - e, 0.0) ** 2).sum(1, keepdim=True) * weight
                      for p, h in zip(preds, held)])
    sq = torch.where(held, sq, math.nan)
    worst = torch.where(held, sq, -math.inf).amax(0, keepdim=True)
    return torch.where(held, sq, torch.where(torch.isfinite(worst), worst, 0.0)), held


def _candidate_z2(preds: list, e: Tensor, weight: Tensor, mask: Tensor, blur: float,
                  others: Tensor | None = None, other_weights: Tensor | None = None) -> Tensor:
    """``z^2`` of each candidate's error in excess of the least one's (:func:`_excess_error_z2`), ``(K, T, 1,
    H, W)``, from its predictions ``preds`` of the samples ``e`` ``(T, 3, H, W)``, the squared residuals
    weighted by ``weight`` and pooled over ``blur`` pixels (with neighbours' ``others`` as there). A candidate
    whose prediction has no support (NaN) is left out at that pixel."""
    sq, held = _squared_residuals(preds, e, weight)
    return _excess_error_z2(sq, mask, blur, held | ~held.any(0, keepdim=True), others, other_weights)


def _excess_error_z2(sq: Tensor, mask: Tensor, blur: float, allowed: Tensor, others: Tensor | None = None,
                     other_weights: Tensor | None = None) -> Tensor:
    """How surely each candidate's error exceeds the least one's: ``z^2`` per candidate and pixel.

    ``sq`` ``(K, T, 1, H, W)`` holds each candidate's weighted squared cross-validation residuals; a pixel's
    error of candidate b is their mean under a Gaussian of ``blur`` pixels (weighted by ``mask``
    ``(T, 1, H, W)``). The excess D of b over the least-error candidate a is the pooled mean of the
    residual differences d = sq_b - sq_a, whose standard error comes from their spread under the same
    kernel: ``var = sum k^2 m (d - D)^2 / (sum k m)^2``. The residuals of two candidates share the sample's
    own noise, so d is far less noisy than either residual; a candidate is out only where the evidence
    says so. ``z^2 = D^2 / var``, 0 for the least-error candidate. Candidates not ``allowed`` (bool, like
    ``sq``) and those whose error exceeds ``_SELECTION_ERROR_CUT`` times the least are left out
    (``_LEFT_OUT``); the least-error allowed candidate never is.

    ``others`` ``(J, K + 1, T, 1, H, W)``: the residual planes of J neighbouring queries
    (:func:`_residual_planes`), which join the kernel in time: each pixel's own residuals weigh 1 and a
    neighbour's ``other_weights`` ``(J, T, 1, H, W)``, normalised (a bias at a place persists from frame to
    frame where the noise does not, so its evidence adds up).
    """
    # in time first: the kernel's weights k (pooled error, pool), their squares k^2 (spreads s1, m2, d2)
    sq_b, mask_b, pair_terms = sq, mask, None
    if others is not None:
        w, total = other_weights, 1.0 + other_weights.sum(0)

        def pooled(own: Tensor, theirs: Tensor, wj: Tensor, power: int) -> Tensor:
            return (own + (wj ** power * theirs).sum(0)) / total ** power
        wk = w[:, None]  # over the candidates
        sq_b, mask_b = pooled(sq, others[:, :-1], wk, 2), pooled(mask, others[:, -1], w, 2)
        pair_terms = {(a, b): pooled((sq[b] - sq[a]) ** 2, (others[:, b] - others[:, a]) ** 2, w, 2)
                      for a in range(sq.shape[0]) for b in range(a + 1, sq.shape[0])}
        sq, mask = pooled(sq, others[:, :-1], wk, 1), pooled(mask, others[:, -1], w, 1)
    K = sq.shape[0]
    pool = footprint_blur(mask, blur).clamp_min(1e-6)
    err = footprint_blur(sq.flatten(0, 1), blur).view_as(sq) / pool
    if blur > 0:  # sum_j k_j^2 f_j = (sum_i k1_i^2)^2 times the blur of f at sigma / sqrt(2)
        c, blur2 = float((_gaussian_taps(blur, torch.float64) ** 2).sum()) ** 2, blur / math.sqrt(2)
    else:
        c, blur2 = 1.0, 0.0
    inv = c / pool ** 2
    s1 = footprint_blur(sq_b.flatten(0, 1), blur2).view_as(sq) * inv
    m2 = footprint_blur(mask_b, blur2) * inv
    pairs = [(a, b) for a in range(K) for b in range(a + 1, K)]
    d2 = {}
    if pairs:
        T = sq.shape[1]
        terms = [(sq[b] - sq[a]) ** 2 if pair_terms is None else pair_terms[a, b] for a, b in pairs]
        blurred = footprint_blur(torch.cat(terms), blur2)
        for k, (a, b) in enumerate(pairs):
            d2[a, b] = d2[b, a] = blurred[k * T:(k + 1) * T] * inv
    best = torch.where(allowed, err, math.inf).argmin(0)  # (T, 1, H, W)
    least = err.gather(0, best[None])[0]
    z2 = torch.zeros_like(err)
    for b in range(K):
        for a in range(K):
            if a != b:
                D = err[b] - err[a]
                var = d2[a, b] - 2 * D * (s1[b] - s1[a]) + D * D * m2
                z2[b] = torch.where(best == a, D.clamp_min(0) ** 2 / var.clamp_min(1e-30), z2[b])
    out = ~allowed | (err > _SELECTION_ERROR_CUT * least)
    keep = torch.arange(K, device=err.device).view(-1, 1, 1, 1, 1) == best
    return torch.where(out & ~keep, _LEFT_OUT, z2)
