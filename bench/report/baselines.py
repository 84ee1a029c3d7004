"""The trivial baselines of every (scene, rate) of the report, on the frames its runs scored: hold the last
anchor, blend the neighbouring anchors, integrate the events onto the last anchor (no model at all)."""

from __future__ import annotations

import numpy as np

from edmcgs.model.eval.baselines import score_baselines
from edmcgs.model.eval.evaluation import summarize
from edmcgs.pipeline import training_data


def baseline_rows(recs: dict, runs: list[dict]) -> list[dict]:
    """One row per (scene, fps, baseline): mean PSNR / SSIM over the frames the runs of that cell scored."""
    out = []
    for scene, fps in sorted({(r["scene"], r["fps"]) for r in runs}):
        run = next(r for r in runs if (r["scene"], r["fps"]) == (scene, fps))
        frames = np.array([f["index"] for f in run["per_frame"]], dtype=np.int64)
        for name, rows in score_baselines(training_data(recs[scene][fps][0]), frames).items():
            s = summarize(rows)
            out.append({"scene": scene, "fps": fps, "baseline": name, "psnr": s["psnr"], "ssim": s["ssim"],
                        "ssim_3dgs": s.get("ssim_3dgs"), "frames": s["frames"]})
    return out
