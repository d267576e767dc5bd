"""What the user can change in the demo: the filter parameters and the keys, as named actions.

:class:`FilterParams` holds the live controls; :mod:`demo.session` maps them onto the one progressive
engine (:class:`torchmanifold.pipeline.progressive.ProgressiveRenderer`). Every key binding is (key name
in moderngl-window's ``Keys``, action, help text), so the same actions run from keys, tests and
scripts. Parameter actions return new :class:`FilterParams` within sane bounds; changing a filter
parameter restarts the progression, because the running buffer was built with the old one.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

from torchmanifold import features as feature_table
from torchmanifold.pipeline import DEFAULT_ALPHA, DenoiseSettings

#: Feature groups the tracer makes (the feature table's groups and tracer channel names); the guide
#: of a feature set is made of the groups the scene provides.
FEATURE_GROUPS = {g: feature_table.tracer_channels(g) for g in feature_table.groups()
                  if feature_table.tracer_channels(g)}

#: Selectable guides (which channels steer the filter). The engine has no colour-guided mode: "colour"
#: guides by every feature the scene provides (see :func:`demo.session.guide_channels`).
FEATURE_SETS = {
    "all": tuple(g for g in FEATURE_GROUPS if feature_table.feature(g).sigma is not None),  # all that can guide
    "albedo+normal+depth": ("Z", "albedo", "N"),
    "albedo+normal": ("albedo", "N"),
    "normal+depth": ("Z", "N"),
    "colour": (),
}

#: How neighbour frames are combined: mean of the window then filter, or joint space-time filter.
TEMPORAL_MODES = ("window", "spacetime")

#: Feature buffers that can be shown instead of the raw image (time last: the least telling to look at).
FEATURE_VIEWS = (*[g for g in FEATURE_GROUPS if g != "T"], "T")

#: The demo's ``sigma_r`` at which the engine's per-group range sigmas apply unscaled; ``sigma_r``
#: multiplies them by ``sigma_r / SIGMA_R_UNSCALED``.
SIGMA_R_UNSCALED = 0.3


@dataclass(frozen=True)
class FilterParams:
    """What the user can change live. Bandwidths are those of the first iteration.

    sigma_s: spatial sigma in pixels. sigma_r: range scale; at ``SIGMA_R_UNSCALED`` every feature group
    has the engine's own range sigma (albedo 0.1, normals 0.3, depth 15% of the scene, ...).
    a: bandwidth reduction in (0, 1). time_window: radius in frames of the temporal Gaussian window
    (0 = each frame filtered alone, the engine's cheapest step and the demo's default: at 128x128 it
    filters in about 0.6x the time of radius 1 and 0.3x of the space-time mode, measured on the
    2-core VM; sigma_t = radius / 2). tree_height: manifold tree height.
    clamp: firefly clamp: 1-spp samples brighter than ``clamp`` times the running estimate are clamped
    (0 = off); the multiple grows as sqrt(iteration), so its bias fades and the result stays consistent.
    temporal_mode: "window" (average the window, then filter: the paper's accumulation) or "spacetime"
    (joint filter, no ghosts of moving objects; slower).
    adaptive: per-pixel bandwidth selection (the denoiser's default: sigma_s x 0.5..4 blended by a
    cross-validated error); off filters at sigma_s alone, the demo's default because it costs about
    three times the filter time (see :class:`torchmanifold.pipeline.DenoiseSettings`).
    """

    sigma_s: float = 3.0
    sigma_r: float = SIGMA_R_UNSCALED
    a: float = DEFAULT_ALPHA  # the pipeline's measured default
    time_window: int = 0
    tree_height: int = 2
    feature_set: str = "albedo+normal+depth"
    clamp: float = DenoiseSettings.firefly_k  # the engine's default threshold
    temporal_mode: str = "window"
    adaptive: bool = False

    def __post_init__(self):
        if not self.sigma_s >= 1.0:
            raise ValueError(f"sigma_s: expected >= 1 pixel, got {self.sigma_s}")
        if not self.sigma_r > 0.0:
            raise ValueError(f"sigma_r: expected > 0, got {self.sigma_r}")
        if not 0.0 < self.a < 1.0:
            raise ValueError(f"a: expected a value in (0, 1), got {self.a}")
        if not (isinstance(self.time_window, int) and self.time_window >= 0):
            raise ValueError(f"time_window: expected an int >= 0 (frames), got {self.time_window!r}")
        if not (isinstance(self.tree_height, int) and 1 <= self.tree_height <= 8):
            raise ValueError(f"tree_height: expected an int in [1, 8], got {self.tree_height!r}")
        if not self.clamp >= 0.0:
            raise ValueError(f"clamp: expected >= 0 (0 = off), got {self.clamp}")
        if self.temporal_mode not in TEMPORAL_MODES:
            raise ValueError(f"temporal_mode: expected one of {TEMPORAL_MODES}, got {self.temporal_mode!r}")
        if self.feature_set not in FEATURE_SETS:
            raise ValueError(f"feature_set: expected one of {sorted(FEATURE_SETS)}, got {self.feature_set!r}")

    def with_(self, **changes) -> "FilterParams":
        return replace(self, **changes)


BINDINGS = (
    ("SPACE", "play", "play / pause the clip"),
    ("LEFT", "scrub_back", "scrub back 1/4 frame (in-between frames)"),
    ("RIGHT", "scrub_forward", "scrub forward 1/4 frame"),
    ("P", "pause_progression", "pause / resume the iterations"),
    ("R", "restart", "restart the progression"),
    ("NUMBER_1", "sigma_s_down", "sigma_s / 1.25"),
    ("NUMBER_2", "sigma_s_up", "sigma_s * 1.25"),
    ("NUMBER_3", "sigma_r_down", "sigma_r / 1.25"),
    ("NUMBER_4", "sigma_r_up", "sigma_r * 1.25"),
    ("NUMBER_5", "a_down", "a - 0.1 (bandwidth reduction)"),
    ("NUMBER_6", "a_up", "a + 0.1"),
    ("NUMBER_7", "window_down", "time window radius - 1 frame"),
    ("NUMBER_8", "window_up", "time window radius + 1 frame"),
    ("T", "temporal_mode", "time window mode: window mean / space-time"),
    ("NUMBER_9", "height_down", "tree height - 1"),
    ("NUMBER_0", "height_up", "tree height + 1"),
    ("G", "feature_set", "next feature set (guide channels)"),
    ("C", "clamp", "firefly clamp on / off"),
    ("B", "adaptive", "per-pixel bandwidth selection on / off (sharper, ~3x filter time)"),
    ("F", "feature_view", "show next feature buffer instead of raw"),
    ("M", "heat_source", "heat map of raw / gaussian / ours"),
    ("MINUS", "exposure_down", "exposure / 1.5"),
    ("EQUAL", "exposure_up", "exposure * 1.5"),
    ("H", "help", "show / hide this help"),
    ("ESCAPE", "quit", "quit"),
)

ACTIONS = tuple(b[1] for b in BINDINGS)


def next_in(seq, current, step: int = 1):
    seq = list(seq)
    return seq[(seq.index(current) + step) % len(seq)] if current in seq else seq[0]


def adjust_params(params: FilterParams, action: str) -> FilterParams | None:
    """The parameters after ``action``, or None if ``action`` is not a parameter action."""
    p = params
    if action == "sigma_s_down":
        return p.with_(sigma_s=max(1.0, p.sigma_s / 1.25))
    if action == "sigma_s_up":
        return p.with_(sigma_s=min(128.0, p.sigma_s * 1.25))
    if action == "sigma_r_down":
        return p.with_(sigma_r=max(0.01, p.sigma_r / 1.25))
    if action == "sigma_r_up":
        return p.with_(sigma_r=min(10.0, p.sigma_r * 1.25))
    if action == "a_down":
        return p.with_(a=round(max(0.1, p.a - 0.1), 4))
    if action == "a_up":
        return p.with_(a=round(min(0.9, p.a + 0.1), 4))
    if action == "window_down":
        return p.with_(time_window=max(0, p.time_window - 1))
    if action == "window_up":
        return p.with_(time_window=min(4, p.time_window + 1))
    if action == "height_down":
        return p.with_(tree_height=max(1, p.tree_height - 1))
    if action == "height_up":
        return p.with_(tree_height=min(5, p.tree_height + 1))
    if action == "temporal_mode":
        return p.with_(temporal_mode=next_in(TEMPORAL_MODES, p.temporal_mode))
    if action == "clamp":
        return p.with_(clamp=0.0 if p.clamp > 0 else FilterParams().clamp)
    if action == "adaptive":
        return p.with_(adaptive=not p.adaptive)
    if action == "feature_set":
        return p.with_(feature_set=next_in(FEATURE_SETS, p.feature_set))
    return None


KEY_LABELS = {"MINUS": "-", "EQUAL": "=", "ESCAPE": "Esc", "SPACE": "Space", "LEFT": "Left", "RIGHT": "Right"}


def help_lines() -> list[str]:
    lines = ["torchmanifold demo: keys", ""]
    for key, _, text in BINDINGS:
        lines.append(f"{KEY_LABELS.get(key, key.replace('NUMBER_', '')):>6}  {text}")
    lines += ["", "Click or drag on the clip bar to scrub.", "Changing a filter parameter restarts", "the progression."]
    return lines
