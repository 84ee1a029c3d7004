"""bench.report.lean on a tiny model: the full twin renders the lean checkpoint's image, and a row states
what was left out and what that saved, with the error inside the stated bound."""

import math

import numpy as np
import torch

from bench.report import lean as report_lean
from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from edmcgs.model.motion import leanness
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, build, perturb_prior


def _half_frozen(tmp_path, **kwargs):
    model, data = build(TINY.replace(sh_degree=3), **kwargs)  # a static camera: degree 0 of 3
    randomize_event_branch(model)
    perturb_prior(model, scale=0.05)
    path = tmp_path / "lean.ckpt"
    save_checkpoint(model, path, freeze_threshold=float(leanness.control_motion_bound(model).median()))
    return path, data


def test_the_full_twin_leaves_nothing_out_and_renders_the_same_image(tmp_path):
    path, data = _half_frozen(tmp_path)
    twin_path = tmp_path / "full.ckpt"
    torch.save(report_lean.full_twin_payload(read_checkpoint(path), data.trajectory), twin_path)
    lean, twin = load_checkpoint(path), load_checkpoint(twin_path)
    assert lean.gaussians.sh_degree == 0 and twin.gaussians.sh_degree == 3
    assert len(lean.meta.trajectory.t_us) == 1 and len(twin.meta.trajectory.t_us) == len(data.trajectory.t_us)
    assert lean.meta.frozen.any() and twin.meta.frozen is None
    lean.meta.frozen = None  # skin every Gaussian: then only the SH storage differs
    t = tiny_scene.T0 + 130_000
    emap = data.event_map(lean.tau(t), t)
    a = lean.render(lean.deform(t, emap), np.eye(4), lean.meta.intrinsics)
    b = twin.render(twin.deform(t, emap), np.eye(4), twin.meta.intrinsics)
    assert np.abs(a - b).max() < 1e-5


def test_a_row_states_what_was_left_out_and_what_it_saved(tmp_path):
    path, data = _half_frozen(tmp_path)
    row = report_lean.measure("tiny", path, data, repeats=1)
    assert (row["sh_degree"], row["sh_max"], row["static_camera"], row["trajectory_poses"]) == (0, 3, True, 1)
    assert row["event_branch"] and row["channels"] == 3
    assert 0 < row["frozen_points"] < row["control_points"] and row["still_gaussians"] > 0
    assert row["bytes_full"] > row["bytes_lean"]  # 16 SH coefficients against 1, three poses against one
    assert 0 < row["max_mean_shift"] <= row["threshold"] * (1 + 1e-4) + 1e-6 and row["within_threshold"]
    assert row["least_motion_of_extent"] <= row["threshold_of_extent"]
    assert row["psnr_lean_vs_full"] > 25 and row["times"] == 5  # three anchors, two held-out frames
    assert row["mid_us"] > row["anchor_us"] and row["mid_events"] > 0
    for key, value in row.items():
        if isinstance(value, float):
            assert math.isfinite(value) and (not key.startswith("ms_") or value > 0), key
    text = "\n".join(report_lean.section([row], {"threads": 1, "repeats": 1, "full_label": "tiny"}))
    assert "| tiny | 3 (colour anchor frames) | 0 (3)" in text and "static: 1 pose" in text
    assert "nan" not in text.lower()


def test_a_grey_row_against_its_rgb_twin(tmp_path):
    model, data = build(TINY.replace(background=(0.55, 0.56, 0.6)), channels=1)  # grey: its luma
    save_checkpoint(model, tmp_path / "grey.ckpt")
    row = report_lean.measure("grey", tmp_path / "grey.ckpt", data, repeats=1)
    assert row["channels"] == 1 and row["channels_why"] == "grey anchor frames"
    assert row["bytes_full"] > row["bytes_lean"]
    assert row["psnr_lean_vs_full"] == report_lean.PSNR_IDENTICAL  # the colour repeated: the same image


def test_grey_recording_keeps_the_luminance_in_one_channel():
    rgb = np.zeros((2, 4, 5, 3), np.uint8)
    rgb[..., 0], rgb[1, ..., 2] = 200, 100
    rec = Recording(width=5, height=4, events=Events.empty(),
                    anchors=Frames(np.array([0, 10], np.int64), rgb), held_out=None)
    grey = report_lean.grey_recording(rec)
    assert grey.anchors.images.shape == (2, 4, 5, 1) and grey.held_out is None
    assert grey.anchors.images[0, 0, 0, 0] == round(0.299 * 200)
    assert grey.anchors.images[1, 0, 0, 0] == round(0.299 * 200 + 0.114 * 100)


def test_the_event_branch_note_times_both_runs_on_the_same_queries(tmp_path):
    paths = {}
    for name, cfg in (("with", TINY), ("without", TINY.replace(events=False))):
        model, data = build(cfg)
        if name == "with":
            randomize_event_branch(model)
        save_checkpoint(model, tmp_path / f"{name}.ckpt")
        paths[name] = tmp_path / f"{name}.ckpt"
    times = report_lean.event_branch_ms(paths["with"], paths["without"], data, repeats=1)
    assert set(times) == {"ms_anchor_with", "ms_anchor_without", "ms_mid_with", "ms_mid_without"}
    assert all(math.isfinite(v) and v > 0 for v in times.values())
    rows = [report_lean.measure(name, path, data, repeats=1) for name, path in paths.items()]
    assert [r["event_branch"] for r in rows] == [True, False]
    context = {"threads": 1, "repeats": 1, "full_label": "with", "no_events_label": "without",
               "event_branch": times}
    text = "\n".join(report_lean.section(rows, context))
    assert f"{times['ms_mid_with']:.2f} ms with it" in text and "without a sensor" in text
