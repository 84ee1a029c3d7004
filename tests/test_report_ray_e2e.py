"""``bench.report --ray``: the grid's runs trained as Ray tasks land in the report's cache, where the
sequential loop then finds them (the same key: the same thread count in the task and the driver)."""

from __future__ import annotations

import pytest

pytest.importorskip("ray", reason="the 'ray' extra is not installed")

from bench.report.training import train_on_ray, train_run
from edmcgs.options import RecordingOptions
from edmcgs.pipeline import open_recording
from harness.server import build_scene

pytestmark = pytest.mark.slow

SMALL = {"init_points": 300, "num_control_points": 16, "deform_width": 16, "deform_depth": 2,
         "substeps": 2, "max_pair_steps": 2}


def test_the_grid_trains_on_ray_into_the_cache(tmp_path):
    import ray
    import torch

    path, _ = build_scene(tmp_path / "rec", width=48, height=32, duration_s=0.6, event_rate=5_000,
                          init_points=300, control_points=16, frames_per_anchor=2)
    rec = open_recording(path, RecordingOptions(anchor_every=2))
    torch.set_num_threads(1)  # the driver's --threads, as bench.report sets it
    jobs = [dict(rec=rec, rec_key="tiny", switches={**SMALL, **switches}, preset="demo", iterations=2,
                 train_scale=None, curve_points=1, device="cpu", cache=tmp_path / "runs", label=label)
            for label, switches in (("full", {}), ("no_events", {"events": False}))]
    results = train_on_ray(jobs, threads=1, num_cpus=2)
    assert not ray.is_initialized()
    assert [r["cached"] for r in results] == [False, False]
    assert results[0]["key"] != results[1]["key"]
    for job, result in zip(jobs, results, strict=True):
        assert (tmp_path / "runs" / result["checkpoint"]).is_file()
        again = train_run(**job, progress=False)  # the sequential loop: found in the cache
        assert again["cached"] is True and again["key"] == result["key"]
        assert again["psnr"] == result["psnr"]


def test_ray_is_given_every_run_the_report_makes(tmp_path):
    from dataclasses import replace

    from bench.report.main import planned_runs
    from bench.report.settings import FULL

    path, _ = build_scene(tmp_path / "rec", width=48, height=32, duration_s=0.6, event_rate=5_000,
                          init_points=300, control_points=16, frames_per_anchor=2)
    rec = open_recording(path, RecordingOptions(anchor_every=2))
    s = replace(FULL, scenes=("a", "b"), fps=(5.0, 10.0), variants=("full", "no_events"),
                sparse_fps=(1.0, 2.0))
    recs = {scene: {f: (rec, f"{scene}{f:g}") for f in (1.0, 2.0, 5.0, 10.0)} for scene in s.scenes}
    cells = planned_runs(s, recs)
    keys = [(*c[:3], c[3][1] if len(c) > 3 else None) for c in cells]
    assert len(keys) == len(set(keys))  # each run once
    grid = {(sc, f, v, None) for sc in s.scenes for f in s.fps for v in s.variants}
    assert grid <= set(keys)
    assert {("a", 1.0, "full", None), ("a", 2.0, "full", None)} <= set(keys)  # the sparse rates
    grey = [c for c in cells if len(c) > 3]
    assert [(c[:3], c[3][1]) for c in grey] == [(("a", 5.0, "full"), "a5_grey")]  # the lean section's
    assert grey[0][3][0].anchors.images.shape[-1] == 1
    assert len(cells) == len(grid) + 3
