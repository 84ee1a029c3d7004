"""bench.report's online section: a recording of the scene four times as long whose first stretch is the
training recording, replayed past a checkpoint with online anchors, scored beside the causal baselines."""

from __future__ import annotations

import numpy as np
import pytest

from bench.online import BAND_S, RENDERS, bands
from bench.report.data import build_config, cached_build
from bench.report.online import SPANS, long_recording, online_rows, section
from bench.report.settings import SMALL
from edmcgs.model.checkpoint import save_checkpoint
from edmcgs.model.config import preset
from edmcgs.pipeline import new_model, training_data

pytestmark = pytest.mark.slow


def test_the_model_is_served_past_its_span_beside_the_baselines(tmp_path):
    s = SMALL.replace(duration_s=0.4, fps=(5.0,), sparse_fps=())
    short, _ = cached_build(build_config("jumpingjack", 5.0, s), tmp_path / "rec", progress=False)
    long, prefix_diff = long_recording("jumpingjack", 5.0, 5.0, short, s, tmp_path / "rec", progress=False)
    assert prefix_diff == 0  # the same simulation: its first stretch is the training recording
    assert len(long.anchors) == SPANS * (len(short.anchors) - 1) + 1
    cfg = preset("demo").replace(init_points=400, num_control_points=24, deform_width=16, deform_depth=2)
    save_checkpoint(new_model(training_data(short), cfg), tmp_path / "short.ckpt")

    rows, predictions, context = online_rows(long, tmp_path / "short.ckpt", short)
    assert "scaled by 0" in context["distilled"]  # an untrained event branch has nothing to distill
    end = short.anchors.t_us[-1]
    assert len(rows) == int((long.held_out.t_us > end).sum()) > 0
    assert len(predictions) == int((long.anchors.t_us > end).sum())
    for p in predictions:  # each new frame scored against its prediction and against its correction
        assert np.isfinite(p["pred_psnr"]) and np.isfinite(p["corrected_psnr"])
    scores = {k: np.mean([p[k] for p in predictions]) for k in ("pred_psnr", "corrected_psnr")}
    assert scores["corrected_psnr"] > scores["pred_psnr"], scores  # the fit moved toward its frame
    for row in rows:
        assert row["since_end_s"] > 0
        assert all(np.isfinite(row[k]) for k in RENDERS)

    # the event branch's ablation runs the same fits: an untrained model's event branch is scaled by 0
    # (its warm-in), so without events it renders what the live chain renders
    assert all(abs(r["live"] - r["no_events"]) < 1e-3 for r in rows)
    summary = bands(rows)
    assert sum(b["frames"] for b in summary) == len(rows)
    assert [b["from_s"] for b in summary] == sorted({BAND_S * (r["since_end_s"] // BAND_S) for r in rows})

    text = "\n".join(section(rows, predictions, context | {"label": "jumpingjack 5 fps",
                                                            "prefix_diff": prefix_diff}))
    assert "## 6. Online anchors past the span" in text and "online_drift.png" in text
    means = {k: np.mean([r[k] for r in rows]) for k in ("live", "hold_last", "hold_projected", "integrate")}
    best = max(means["hold_last"], means["hold_projected"], means["integrate"])
    verdict = "beats" if means["live"] > best else "does not beat"
    assert f"The live render {verdict} the three causal baselines" in text
    assert f"| hold the last anchor frame (no model) | {means['hold_last']:.2f} |" in text
