"""What one run of ``python -m bench.report`` covers: the small default (minutes on a 2-core CPU) and
``--full`` (the paper's grid: four scenes at 5 and 10 fps, every ablation, 3000 steps per run)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

VARIANTS = {
    "full": ({}, "Full"),
    "no_events": ({"events": False}, "w/o event stream"),
    "no_markov": ({"markov": False}, "w/o Markov chain"),
    "no_local_sampling": ({"local_sampling": False}, "w/o local sampling"),
    "no_tli": ({"tli": False}, "w/o TLI"),
}
"""Variant key -> (config switches, the paper's row label)."""


@dataclass(frozen=True)
class ReportSettings:
    """One report's grid and budgets."""

    name: str
    """"small" or "full" (written into the summary)."""
    scenes: tuple[str, ...]
    """Synthetic scenes (``edmcgs.synth.scene.SCENES``)."""
    fps: tuple[float, ...]
    """Anchor frame rates of the ablation table."""
    variants: tuple[str, ...]
    """Keys of ``VARIANTS``."""
    size: str
    """Scene size: "small" (173x130) or "full" (346x260)."""
    duration_s: float | None
    """Sequence length; None: the scene's own (2 s)."""
    held_out_per_interval: int
    """Ground-truth frames per anchor interval at the highest frame rate (lower rates derived from it get
    more: see ``report_data.fewer_anchors``)."""
    dt_min_us: int
    """Finest step of the event simulator's adaptive sampling."""
    dt_max_us: int
    """Coarsest step of the event simulator's adaptive sampling."""
    preset: str
    """Model preset (``edmcgs.model.config.PRESETS``)."""
    iterations: int
    """Training steps per run."""
    train_scale: float | None
    """Training render scale (evaluation is always at full resolution); None: the preset's."""
    curve_points: int
    """Evaluations along each training run (plus one before the first step), on every held-out frame."""
    render_scales: tuple[float, ...]
    """Resolution knob of the render sweep, as fractions of the scene's size."""
    render_repeats: int
    """Timed repeats per render setting (the median is reported)."""
    sparse_fps: tuple[float, ...]
    """Anchor rates of the stability section's sparse-anchor runs."""
    precision_scenes: int
    """How many scenes get the float32-vs-float64 comparison against the (slow) reference renderer."""

    def replace(self, **changes) -> ReportSettings:
        return dataclasses.replace(self, **changes)


SMALL = ReportSettings(
    name="small", scenes=("jumpingjack",), fps=(5.0, 10.0), variants=tuple(VARIANTS), size="small",
    duration_s=1.0, held_out_per_interval=4, dt_min_us=1000, dt_max_us=8000, preset="demo", iterations=200,
    train_scale=None, curve_points=5, render_scales=(0.25, 0.5, 1.0), render_repeats=5,
    sparse_fps=(1.0, 2.0), precision_scenes=1)
"""Minutes on a shared 2-core CPU: one scene, 1 s, 200 steps per run. A smoke-scale view, not the paper's."""

FULL = ReportSettings(
    name="full", scenes=("jumpingjack", "kick", "mutant", "lego"), fps=(5.0, 10.0), variants=tuple(VARIANTS),
    size="small", duration_s=None, held_out_per_interval=4, dt_min_us=250, dt_max_us=4000, preset="demo",
    iterations=3000, train_scale=None, curve_points=10, render_scales=(0.25, 0.5, 1.0, 2.0),
    render_repeats=9, sparse_fps=(1.0, 2.0), precision_scenes=4)
"""The paper's grid (4 scenes x 2 rates x 5 variants), the demo preset at 3000 steps (twice its own): hours
on a CPU."""
