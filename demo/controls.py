"""Key bindings of the demo as named actions, so the same actions run from keys, tests and scripts.

Every binding is (key name in moderngl-window's ``Keys``, action, help text). Parameter actions
return new :class:`~demo.progression.FilterParams` within sane bounds; changing a filter parameter
restarts the progression, because the running buffer was built with the old one.
"""
from __future__ import annotations

from demo.progression import FEATURE_SETS, TEMPORAL_MODES, FilterParams

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
        return p.with_(clamp=0.0 if p.clamp > 0 else FilterParams().clamp or 4.0)
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
