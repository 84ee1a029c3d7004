"""``edmcgs train --ray``: several recordings trained as Ray tasks on a local Ray (2 CPUs), their
checkpoints where the sequential run writes them."""

from __future__ import annotations

import pytest

pytest.importorskip("ray", reason="the 'ray' extra is not installed")

from edmcgs.cli import main
from edmcgs.model.checkpoint import load_checkpoint
from harness.server import build_scene

pytestmark = pytest.mark.slow

TINY = ["init_points=300", "num_control_points=16", "deform_width=16", "deform_depth=2", "iterations=2",
        "substeps=2", "max_pair_steps=2", "eval_every=0", "checkpoint_every=0", "train_scale=1.0"]


def test_recordings_train_side_by_side_on_ray(tmp_path, capsys):
    import ray

    recordings = []
    for name, seed in (("east", 1), ("west", 2)):
        rec, _ = build_scene(tmp_path / name, width=48, height=32, duration_s=0.6, event_rate=5_000,
                             init_points=300, control_points=16, seed=seed)
        recordings.append(rec.rename(tmp_path / name / f"{name}.h5"))
    out = tmp_path / "models"
    args = ["train", *map(str, recordings), "-o", str(out), "--ray", "--ray-cpus", "2", "--threads", "1",
            *[a for s in TINY for a in ("--set", s)]]
    assert main(args) == 0
    assert not ray.is_initialized(), "the local Ray started for the runs is shut down"
    for rec in recordings:
        assert load_checkpoint(out / f"{rec.stem}.ckpt").meta.event_width == 48
    printed = capsys.readouterr().out
    assert f"{recordings[1]}: wrote {out / 'west.ckpt'}" in printed


def test_a_failing_run_fails_the_command(tmp_path, capsys):
    import h5py

    bad = tmp_path / "bad.h5"
    with h5py.File(bad, "w") as f:  # an HDF5 file passes the command's checks: its Ray task fails
        f["unrelated"] = [1, 2, 3]
    args = ["train", str(bad), "-o", str(tmp_path / "m"), "--ray", "--ray-cpus", "2",
            *[a for s in TINY for a in ("--set", s)]]
    assert main(args) == 1
    assert f"{bad}: FAILED" in capsys.readouterr().out
