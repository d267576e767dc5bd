"""Every denoising method the benchmarks and the stability suite compare, behind one interface.

This is the ONE method registry: ``benchmarks/bench_*.py`` and ``tests/stability`` both import it.

A method denoises one query frame of a :class:`Clip`::

    out = method(clip, query=2, sigma_s=8.0, sigma_r=0.3)      # (C, H, W), clip.values.dtype

* ``clip.values`` (T, C, H, W) noisy linear colour, ``clip.guide`` (T, D, H, W) guide features already scaled so
  that ``sigma_r`` applies to every channel (the convention of ``torchmanifold.adaptive_manifold_filter``),
  ``clip.times`` (T,) frame times, optional raw ``clip.albedo`` / ``clip.normal`` (T, 3, H, W) for OIDN.
* Spatial methods use only frame ``query``; temporal ones (``Method.temporal``) use every frame of the clip, so the
  caller slices the time window it wants around the query. A method that ``streams`` gets the whole clip
  and its queries in frame order, and keeps what it derived from each frame for the windows after (as the
  ``denoise`` command does), so its time per frame is the command's, not a window's worth of per-frame work.
* ``Method.params`` overrides the call's arguments: ``gaussian-s2`` always blurs with sigma 2, whatever
  ``sigma_s`` says. The stability registry leaves them empty so a case's sigmas reach every method.

Methods whose library is missing are listed with ``available=False`` and the import error in ``why``, never hidden.
Plain path tracing with more samples is not a filter; the benchmarks add it as a rendering point themselves.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch


@dataclass
class Clip:
    """A denoising problem: T frames of noisy colour, guide features and times.

    Args:
        values: (T, C, H, W) noisy linear colour (any float dtype).
        guide: (T, D, H, W) guide, scaled so one ``sigma_r`` applies to every channel.
        times: (T,) frame times in frames.
        guide_names: names of the D guide channels (for reports).
        albedo: optional (T, 3, H, W) raw albedo in [0, 1] (OIDN's auxiliary input).
        normal: optional (T, 3, H, W) raw normals in [-1, 1] (OIDN's auxiliary input).
        features: optional (T, F, H, W) raw features named ``feature_names`` (the pipeline's input).
        emission: optional (T, 3, H, W) emitted radiance at the first hit, part of ``values`` (the pipeline
            keeps it out of the filter).
        samples_per_pixel: the sample count of ``values`` when known (the pipeline's footprint width).
    """

    values: torch.Tensor
    guide: torch.Tensor
    times: torch.Tensor
    guide_names: tuple = ()
    albedo: Optional[torch.Tensor] = None
    normal: Optional[torch.Tensor] = None
    features: Optional[torch.Tensor] = None
    feature_names: tuple = ()
    emission: Optional[torch.Tensor] = None
    samples_per_pixel: Optional[int] = None

    def __post_init__(self):
        if self.values.dim() != 4 or self.guide.dim() != 4:
            raise ValueError(
                f"Clip: values and guide must be (T, C, H, W) and (T, D, H, W), got {tuple(self.values.shape)} "
                f"and {tuple(self.guide.shape)}")
        if self.values.shape[0] != self.guide.shape[0] or self.values.shape[-2:] != self.guide.shape[-2:]:
            raise ValueError(
                f"Clip: guide {tuple(self.guide.shape)} must match values {tuple(self.values.shape)} in T, H, W")
        if self.times.shape != (self.values.shape[0],):
            raise ValueError(f"Clip: times must be ({self.values.shape[0]},), got {tuple(self.times.shape)}")

    def window(self, query: int, radius: int) -> tuple["Clip", int]:
        """The frames within ``radius`` of ``query`` as a new clip, and the query's index inside it."""
        from torchmanifold.timewindow import index_window

        span = index_window(self.values.shape[0], query, radius)
        lo, hi = span.start, span.stop
        pick = (lambda x: None if x is None else x[lo:hi])
        return Clip(self.values[lo:hi], self.guide[lo:hi], self.times[lo:hi], self.guide_names, pick(self.albedo),
                    pick(self.normal), pick(self.features), self.feature_names, pick(self.emission),
                    self.samples_per_pixel), query - lo


@dataclass
class Method:
    """One denoiser: ``fn(clip, query, sigma_s, sigma_r, **params) -> (C, H, W)``.

    ``raw_input``: the method wants the renderer's colour as it is (OIDN, our pipeline, which demodulate and
    treat fireflies themselves), not the demodulated irradiance the benchmarks give the plain filters.
    ``streams``: a temporal method that takes the whole clip, queries in frame order (see the module's notes).
    """

    name: str
    family: str
    fn: Callable
    params: dict = field(default_factory=dict)
    temporal: bool = False
    available: bool = True
    why: str = ""
    raw_input: bool = False
    streams: bool = False

    def __call__(self, clip: Clip, query: int = 0, sigma_s: float = 8.0, sigma_r: float = 0.3) -> torch.Tensor:
        if not self.available:
            raise RuntimeError(f"method {self.name!r} is not installed: {self.why}")
        kwargs = {"sigma_s": sigma_s, "sigma_r": sigma_r, **self.params}
        return self.fn(clip, query, **kwargs)


# ---------------------------------------------------------------------------------------------------- wrappers
def _fit_kernel(sigma: float, h: int, w: int, cap: int = 10**9) -> int:
    """Odd kernel of +-3 sigma, shrunk so reflect padding fits the image (kornia needs pad < size)."""
    k = 2 * math.ceil(3.0 * sigma) + 1
    return max(1, min(k, cap, 2 * min(h, w) - 1) | 1)


def _gaussian(clip: Clip, query: int, sigma_s: float, sigma_r: float) -> torch.Tensor:
    import kornia

    x = clip.values[query : query + 1]
    k = _fit_kernel(sigma_s, *x.shape[-2:])
    return kornia.filters.gaussian_blur2d(x, (k, k), (float(sigma_s), float(sigma_s)))[0]


def _joint_bilateral(clip: Clip, query: int, sigma_s: float, sigma_r: float, max_kernel: int = 9) -> torch.Tensor:
    import kornia

    x, g = clip.values[query : query + 1], clip.guide[query : query + 1]
    # A dense kernel costs k^2 per pixel: cap it (the spatial sigma still applies inside it).
    k = _fit_kernel(sigma_s, *x.shape[-2:], cap=max_kernel)
    return kornia.filters.joint_bilateral_blur(
        x, g.to(x.dtype), k, float(sigma_r), (float(sigma_s), float(sigma_s)), color_distance_type="l2")[0]


def _to_hwc(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(torch.float32).permute(1, 2, 0).numpy())


def _from_hwc(a: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    if a.ndim == 2:
        a = a[:, :, None]
    return torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1).to(like.dtype)


def _opencv_am(clip: Clip, query: int, sigma_s: float, sigma_r: float, adjust_outliers: bool = False):
    import cv2

    x, g = clip.values[query], clip.guide[query]
    # OpenCV wants float32 HWC (its own docs: 8/16-bit guides are rescaled); feed it what it accepts.
    out = cv2.ximgproc.amFilter(_to_hwc(g), _to_hwc(x), float(sigma_s), float(sigma_r),
                                adjust_outliers=bool(adjust_outliers))
    return _from_hwc(out, x)


_OIDN: dict = {}  # threads -> (device, {(H, W, albedo?, normal?): filter})


def _oidn_run(color: np.ndarray, albedo, normal) -> np.ndarray:
    """OIDN's RT filter (HDR) on its own device with as many threads as torch uses, so its time is comparable.

    pyoidn.denoise() would run OIDN's thread pool over every core whatever the benchmark's thread setting.
    Device and filter are kept between calls (as pyoidn.denoise does); images are re-bound every call."""
    import pyoidn

    threads = torch.get_num_threads()
    if threads not in _OIDN:
        dev = pyoidn.Device()
        dev.set_int("numThreads", threads)
        dev.commit()
        _OIDN[threads] = (dev, {})
    dev, filters = _OIDN[threads]
    key = (*color.shape[:2], albedo is not None, normal is not None)
    flt = filters.get(key)
    if flt is None:
        flt = filters[key] = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
        flt.set_bool("hdr", True)
    out = np.empty_like(color)
    for name, img in ((pyoidn.OIDN_IMAGE_COLOR, color), (pyoidn.OIDN_IMAGE_ALBEDO, albedo),
                      (pyoidn.OIDN_IMAGE_NORMAL, normal), (pyoidn.OIDN_IMAGE_OUTPUT, out)):
        if img is not None:
            flt.set_image(name, img, pyoidn.OIDN_FORMAT_FLOAT3)
    flt.commit()
    flt.execute()
    err = dev.get_error()
    if err:
        filters.pop(key).release()
        raise RuntimeError(f"OIDN: {err}")
    return out


def _oidn(clip: Clip, query: int, sigma_s: float, sigma_r: float, aux: bool = True) -> torch.Tensor:
    x = clip.values[query]
    if x.shape[0] != 3:
        # OIDN denoises RGB only: run each channel on its own as a grey image.
        grey = [Clip(c[None, None].expand(1, 3, -1, -1), clip.guide[query : query + 1], clip.times[:1]) for c in x]
        return torch.cat([_oidn(g, 0, sigma_s, sigma_r, aux=False)[:1] for g in grey])
    albedo = normal = None
    if aux and clip.albedo is not None:
        albedo = _to_hwc(clip.albedo[query].clamp(0, 1))
    if aux and clip.normal is not None and albedo is not None:  # OIDN takes a normal only beside an albedo
        normal = _to_hwc(clip.normal[query].clamp(-1, 1))
    return _from_hwc(_oidn_run(_to_hwc(x), albedo, normal), x)


def _ours(clip: Clip, query: int, sigma_s: float, sigma_r: float, tree_height: int = 2,
          adjust_outliers: bool = False) -> torch.Tensor:
    import torchmanifold

    x, g = clip.values[query : query + 1], clip.guide[query : query + 1]
    return torchmanifold.adaptive_manifold_filter(x, g.to(x.dtype), sigma_s, sigma_r, tree_height=tree_height,
                                                  adjust_outliers=adjust_outliers)[0]


def _pipeline(clip: Clip, query: int, sigma_s: float, sigma_r: float, **settings) -> torch.Tensor:
    """Our product: ``torchmanifold.pipeline.denoise_frames`` with its own preprocessing (demodulation, firefly
    treatment, guide sigmas) on the raw colour and features; sigma_s / sigma_r of the call are not used. With a
    ``temporal_radius`` the clip's frames (the harness' window around the query) join at the query's time."""
    from torchmanifold.pipeline import DenoiseSettings, denoise_frames

    if clip.features is None:
        raise ValueError("the pipeline needs the clip's raw features (Clip.features)")
    st = DenoiseSettings(**settings)
    emission = clip.emission
    if st.temporal_radius == 0:  # one frame: its statistics are its own, the others' cost nothing
        q = slice(query, query + 1)
        return denoise_frames(clip.values[q], clip.features[q], clip.feature_names,
                              None if emission is None else emission[q], settings=st,
                              samples_per_pixel=clip.samples_per_pixel)[0]
    times = [float(t) for t in clip.times]
    return denoise_frames(clip.values, clip.features, clip.feature_names, emission, settings=st,
                          frame_times=times, query_times=[times[query]], samples_per_pixel=clip.samples_per_pixel)[0]


class _PipelineStream:
    """:func:`_pipeline` with a time window, the way the ``denoise`` command runs it: each frame of the clip
    prepared once (``prepare_frames``), each query filtered from its window's prepared frames
    (``denoise_prepared``); the same bytes as ``denoise_frames`` on the window. Queries come in frame order;
    another clip, other settings or an earlier query start afresh."""

    def __init__(self):
        self._clip, self._settings, self._frames, self._last = None, None, None, -1

    def __call__(self, clip: Clip, query: int, sigma_s: float, sigma_r: float, **settings) -> torch.Tensor:
        from torchmanifold.pipeline.denoise import (DenoiseSettings, FrameState, adapt_to_features,
                                                    denoise_prepared, prepare_frames)
        from torchmanifold.pipeline.selection import ClipCache
        from torchmanifold.pipeline.sliding import SlidingFrames
        from torchmanifold.timewindow import index_window

        if clip.features is None:
            raise ValueError("the pipeline needs the clip's raw features (Clip.features)")
        names = list(clip.feature_names)
        st = adapt_to_features(DenoiseSettings(**settings).check(), names)[0]
        if clip is not self._clip or st != self._settings or query < self._last:
            em = clip.emission

            def prepare(k: int, _) -> FrameState:
                return prepare_frames(clip.values[k:k + 1], clip.features[k:k + 1], names,
                                      None if em is None else em[k:k + 1], st,
                                      samples_per_pixel=clip.samples_per_pixel)

            self._clip, self._settings, self._frames = clip, st, SlidingFrames(lambda k: k, prepare)
            self._candidates = ClipCache()
        self._last = query
        r = st.window_radius
        ids = list(index_window(clip.values.shape[0], query, r))
        times = [float(clip.times[k]) for k in ids]
        states = FrameState.cat(self._frames.prepared(ids))
        self._candidates.release_before(times[0])
        return denoise_prepared(states, st, times, [float(clip.times[query])],
                                cache=self._candidates)[0].to(clip.values.dtype)


def _ours_temporal(clip: Clip, query: int, sigma_s: float, sigma_r: float, tree_height: int = 2,
                   mode: str = "window", sigma_t: float = 1.0, adjust_outliers: bool = False) -> torch.Tensor:
    import torchmanifold

    x = clip.values[None]
    g = clip.guide[None].to(x.dtype)
    out = torchmanifold.temporal_adaptive_manifold_filter(
        x, g, clip.times.to(torch.float32), clip.times[query : query + 1].to(torch.float32), sigma_s, sigma_r,
        sigma_t=sigma_t, mode=mode, tree_height=tree_height, adjust_outliers=adjust_outliers)
    return out[0, 0]


# ---------------------------------------------------------------------------------------------------- registry
def _probe(module: str, attr: Optional[str] = None) -> tuple[bool, str]:
    try:
        mod = __import__(module, fromlist=["_"])
        if attr is not None:
            obj = mod
            for part in attr.split("."):
                obj = getattr(obj, part)
        return True, ""
    except Exception as exc:  # an ImportError or a missing attribute: the method is reported as unavailable
        return False, f"{type(exc).__name__}: {exc}"


def _entry(name, family, fn, probe, params=None, temporal=False, raw_input=False, streams=False) -> Method:
    ok, why = probe
    return Method(name, family, fn, dict(params or {}), temporal, ok, why, raw_input, streams)


def stability_methods() -> list[Method]:
    """One entry per method family, taking each case's sigma_s / sigma_r (what the stability suite runs)."""
    kornia_ok = _probe("kornia", "filters.joint_bilateral_blur")
    ours_ok = _probe("torchmanifold", "adaptive_manifold_filter")
    ours_t_ok = _probe("torchmanifold", "temporal_adaptive_manifold_filter")
    return [
        _entry("gaussian", "gaussian", _gaussian, kornia_ok),
        _entry("joint-bilateral", "joint-bilateral", _joint_bilateral, kornia_ok),
        _entry("opencv-am", "opencv-am", _opencv_am, _probe("cv2", "ximgproc.amFilter")),
        _entry("oidn", "oidn", _oidn, _probe("pyoidn", "Filter"), raw_input=True),
        _entry("ours-H1", "ours", _ours, ours_ok, {"tree_height": 1}),
        _entry("ours-H2", "ours", _ours, ours_ok, {"tree_height": 2}),
        _entry("ours-H4", "ours", _ours, ours_ok, {"tree_height": 4}),
        _entry("ours-H2-window", "ours", _ours_temporal, ours_t_ok, {"mode": "window"}, temporal=True),
        _entry("ours-H2-spacetime", "ours", _ours_temporal, ours_t_ok, {"mode": "spacetime"}, temporal=True),
    ]


def benchmark_methods(sigma_s: float = 8.0, sigma_r: float = 0.3, sigma_t: float = 1.0,
                      gaussian_sigmas=(1.0, 2.0, 4.0, 8.0), bilateral_sigma_r=(0.3, 1.0),
                      heights=(1, 2, 3, 4)) -> list[Method]:
    """The methods of the speed-accuracy comparison, each with its settings fixed in ``params``."""
    kornia_ok = _probe("kornia", "filters.joint_bilateral_blur")
    cv_ok = _probe("cv2", "ximgproc.amFilter")
    ours_ok = _probe("torchmanifold", "adaptive_manifold_filter")
    ours_t_ok = _probe("torchmanifold", "temporal_adaptive_manifold_filter")
    out = [_entry(f"gaussian-s{s:g}", "gaussian", _gaussian, kornia_ok, {"sigma_s": s}) for s in gaussian_sigmas]
    out += [_entry(f"joint-bilateral-r{r:g}", "joint-bilateral", _joint_bilateral, kornia_ok,
                   {"sigma_s": min(sigma_s, 3.0), "sigma_r": r}) for r in bilateral_sigma_r]
    # amFilter picks its tree height itself from the sigmas.
    out += [_entry("opencv-am", "opencv-am", _opencv_am, cv_ok, {"sigma_s": sigma_s, "sigma_r": sigma_r})]
    out += [_entry("oidn", "oidn", _oidn, _probe("pyoidn", "Filter"), raw_input=True)]
    out += [_entry(f"ours-H{h}", "ours", _ours, ours_ok, {"sigma_s": sigma_s, "sigma_r": sigma_r, "tree_height": h})
            for h in heights]
    out += [_entry(f"ours-H2-{m}", "ours", _ours_temporal, ours_t_ok,
                   {"sigma_s": sigma_s, "sigma_r": sigma_r, "sigma_t": sigma_t, "mode": m}, temporal=True)
            for m in ("window", "spacetime")]
    pipe_ok = _probe("torchmanifold.pipeline", "denoise_frames")
    from torchmanifold.pipeline.denoise_files import COMMAND_FILTER
    out += [_entry("ours-pipeline", "ours", _pipeline, pipe_ok, raw_input=True),
            # the denoise command's default (COMMAND_FILTER: +-2 frames, joint space-time), each frame
            # prepared once
            _entry("ours-pipeline-spacetime", "ours-spacetime", _PipelineStream(), pipe_ok,
                   {**COMMAND_FILTER, "mode": "spacetime"}, temporal=True, raw_input=True, streams=True)]
    return out


def by_name(methods: list[Method]) -> dict:
    return {m.name: m for m in methods}
