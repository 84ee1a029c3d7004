"""``edmcgs train REC -o CKPT --ray --workers 2``: one recording trained data-parallel on Ray Train (a
local Ray of 2 CPUs, gloo), the one checkpoint laid out as a single-process run's, loading and rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("ray.train", reason="the 'ray' extra (ray[train]) is not installed")

from edmcgs.cli import main
from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
from harness.server import build_scene

pytestmark = pytest.mark.slow

# The real preset (anchor windows: each worker draws its shard's windows, the rows exchanged), tiny.
TINY_REAL = ["iterations=1", "steps_per_window=4", "num_control_points=4", "control_points_per_window=4",
             "init_points=150", "init_points_per_window=150", "graph_k=3",
             "deform_width=16", "deform_depth=2", "substeps=2", "max_pair_steps=2", "eval_every=0",
             "checkpoint_every=0"]


def _train(rec, out, *extra) -> int:
    return main(["train", str(rec), "-o", str(out), "--config", "real", "--anchor-every", "2",
                 "--threads", "1", "-q", *[a for s in TINY_REAL for a in ("--set", s)], *extra])


def test_two_workers_write_the_one_checkpoint_a_single_run_writes(tmp_path, capsys, monkeypatch):
    import ray

    rec, _ = build_scene(tmp_path / "scene", width=48, height=32, duration_s=0.8, event_rate=20_000,
                         frames_per_anchor=2, init_points=300, control_points=16, seed=3)
    single, parallel = tmp_path / "single.ckpt", tmp_path / "parallel.ckpt"
    assert _train(rec, single) == 0
    monkeypatch.chdir(tmp_path)  # paths relative to here: the workers run elsewhere
    assert _train(rec.relative_to(tmp_path), parallel.name, "--ray", "--workers", "2", "--ray-cpus", "2") == 0
    assert not ray.is_initialized(), "the local Ray started for the run is shut down"
    printed = capsys.readouterr().out
    assert f"wrote {parallel.name}" in printed and "held-out PSNR" in printed
    a, b = read_checkpoint(single), read_checkpoint(parallel)
    assert a.keys() == b.keys() and a["sizes"] == b["sizes"] and a["meta"].keys() == b["meta"].keys()
    assert {k: tuple(v.shape) for k, v in a["state_dict"].items()} == \
        {k: tuple(v.shape) for k, v in b["state_dict"].items()}
    assert b["meta"]["config"] == a["meta"]["config"]
    assert (parallel.parent / "parallel.ckpt.train-state").exists()  # resumable like a single run's
    # a step averages both workers' samples: the groups every sample moves take Adam's square-root rate,
    # a window's Gaussians (drawn as often as in one process) their own
    lr = {}
    for name, path in (("single", single), ("parallel", parallel)):
        state = torch.load(f"{path}.train-state", weights_only=False)["train_state"]["optimizer"]
        lr[name] = {g["name"]: g["lr"] for g in state["param_groups"]}
    # (the groups of a fixed rate: the decaying ones end one step apart)
    assert lr["parallel"]["radius"] == pytest.approx(math.sqrt(2) * lr["single"]["radius"], rel=1e-6)
    for group in ("quats", "features", "opacity_logits"):
        assert lr["parallel"][group] == pytest.approx(lr["single"][group], rel=1e-6)
    model = load_checkpoint(parallel)
    t = int(model.meta.anchors_us[1]) + 20_000
    image = model.render(model.deform(t), model.meta.trajectory.at(t), model.meta.intrinsics)
    assert image.shape == (32, 48, 3) and np.isfinite(image).all() and image.max() > 0


def test_workers_need_ray_and_one_recording(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["train", "a.h5", "-o", str(tmp_path / "m.ckpt"), "--workers", "2"])
    assert "give --ray too" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "a.h5", "b.h5", "-o", str(tmp_path / "m"), "--ray", "--workers", "2"])
    assert "trains one recording" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "a.h5", "-o", str(tmp_path / "m.ckpt"), "--ray", "--workers", "2", "--compile"])
    assert "--compile are for a single process" in capsys.readouterr().err
