"""Scores side by side: the model, its baselines (and any ablation) on the same held-out frames, overall
and by time since the anchor, with the baselines a method loses to named."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from edmcgs.model.eval.evaluation import FrameScore, summarize

SSIM_NOTE = ("SSIM: 11x11 Gaussian windows inside the image only; SSIM (3DGS): the 3DGS papers' convention, "
             "zero-padded windows over the full image, the one comparable with their numbers")
"""What the two SSIM columns of every table mean (``ssim.py``)."""


@dataclass
class Comparison:
    """``rows[name]``: per-frame scores of each method, every method on the same frames."""

    rows: dict[str, list[FrameScore]]

    def __post_init__(self) -> None:
        frames = {name: [r.index for r in rows] for name, rows in self.rows.items()}
        if len({tuple(v) for v in frames.values()}) > 1:
            raise ValueError("every method must be scored on the same frames")

    def summary(self) -> dict[str, dict[str, float]]:
        return {name: summarize(rows) for name, rows in self.rows.items()}

    def time_bins(self, bins: int = 4) -> np.ndarray:
        """Edges (µs since the anchor) of ``bins`` equal bins up to the longest wait in the data."""
        waits = [r.t_us - r.anchor_us for rows in self.rows.values() for r in rows]
        return np.linspace(0, max(waits, default=0) + 1, bins + 1)

    def by_time(self, edges: np.ndarray) -> dict[str, list[float]]:
        """Mean PSNR per bin of time since the anchor (NaN for an empty bin)."""
        out = {}
        for name, rows in self.rows.items():
            wait = np.array([r.t_us - r.anchor_us for r in rows], dtype=np.float64)
            value = np.array([r.psnr for r in rows])
            out[name] = [float(value[(wait >= a) & (wait < b)].mean()) if np.any((wait >= a) & (wait < b))
                         else float("nan") for a, b in itertools.pairwise(edges)]
        return out

    def losses(self, method: str, to: tuple[str, ...]) -> list[str]:
        """One line per method in ``to`` that ``method`` does not beat on mean PSNR."""
        summary = self.summary()
        mine = summary[method]["psnr"]
        return [f"{method} loses to {name} by {summary[name]['psnr'] - mine:.2f} dB PSNR"
                for name in to if name in summary and not mine > summary[name]["psnr"]]

    def markdown(self, bins: int = 4) -> str:
        """A table: mean PSNR / SSIM (both conventions), then PSNR by time since the anchor."""
        edges = self.time_bins(bins)
        heads = [f"{a / 1000:.0f}-{b / 1000:.0f} ms" for a, b in itertools.pairwise(edges)]
        n = len(next(iter(self.rows.values()), []))
        lines = [f"| {n} held-out frames | PSNR (dB) | SSIM | SSIM (3DGS) | " + " | ".join(heads) + " |",
                 "|---|---:|---:|---:|" + "---:|" * len(heads)]
        timed = self.by_time(edges)
        for name, s in self.summary().items():
            cells = " | ".join("" if np.isnan(v) else f"{v:.2f}" for v in timed[name])
            s3 = f"{s['ssim_3dgs']:.4f}" if "ssim_3dgs" in s else "—"
            lines.append(f"| {name} | {s['psnr']:.2f} | {s['ssim']:.4f} | {s3} | {cells} |")
        lines.append("")
        lines.append("(PSNR by time since the anchor the frame is rendered from, in the last columns; "
                     f"{SSIM_NOTE})")
        return "\n".join(lines)
