"""EdMCGS end to end on a tiny scene: construction, the inference API's invariants, checkpoints, training."""

import math
import os

import numpy as np
import pytest
import torch

from edmcgs.errors import CheckpointError, InvalidInputError
from edmcgs.model.checkpoint import (
    FORMAT,
    VERSION,
    checksum,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from edmcgs.model.motion.event_branch import FIELD
from edmcgs.model.train.trainer import Trainer
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, build, states_equal


def test_untrained_model_meta_and_tau():
    model, _ = build()
    meta = model.meta
    assert meta.t_start_us == tiny_scene.T0 and meta.t_end_us == tiny_scene.T0 + 200_000
    assert meta.anchors_us.dtype == np.int64 and meta.channels == 3 and meta.has_event_branch
    assert (meta.event_width, meta.event_height) == (tiny_scene.W, tiny_scene.H)
    assert model.tau(tiny_scene.T0 + 150_000) == tiny_scene.T0 + 100_000
    assert model.tau(tiny_scene.T0 + 100_000) == tiny_scene.T0 + 100_000
    assert model.tau(tiny_scene.T0 + 999_999) == tiny_scene.T0 + 200_000
    with pytest.raises(InvalidInputError, match="before the first anchor"):
        model.tau(tiny_scene.T0 - 1)
    with pytest.raises(InvalidInputError, match="t_us"):
        model.tau(1.5)
    assert len(model.gaussians) == TINY.init_points
    assert meta.normalized_time(tiny_scene.T0 + 100_000) == 0.5


def test_empty_window_at_an_anchor_is_exactly_the_anchor_state():
    model, _ = build()
    randomize_event_branch(model)
    with torch.no_grad():
        for p in model.prior.parameters():
            p.add_(torch.randn_like(p) * 0.1)
    t = tiny_scene.T0 + 100_000
    anchor = model.deform(t)
    zeros = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
    assert states_equal(anchor, model.deform(t, zeros))
    assert states_equal(anchor, model.deform(t, torch.zeros(tiny_scene.H, tiny_scene.W)))
    assert states_equal(anchor, model.deform(t, None, np.eye(4)))
    events = zeros.copy()
    events[10:20, 10:20] = 3.0
    # At the anchor itself the window [tau, t) is empty whatever map is passed: the branch is skipped.
    assert states_equal(anchor, model.deform(t, events))
    moved = model.deform(t + 1, events)
    assert not torch.equal(moved.means, model.deform(t + 1).means)
    assert torch.isfinite(moved.means).all()


def test_event_branch_is_local():
    model, _ = build(TINY.replace(event_pool=1))  # a 23-px field: local within this 48x32 image
    randomize_event_branch(model)
    t = tiny_scene.T0 + 50_000
    cp = model.control.positions
    emap = torch.zeros(tiny_scene.H, tiny_scene.W)
    emap[:6, :6] = 2.0  # events in the top-left corner only
    trans_ev, _, disp = model.control_motion(0.25, emap, torch.eye(4))
    from edmcgs.geometry import project
    uv, _ = project(cp, torch.eye(4), model.meta.intrinsics)
    far = (uv[:, 0] > 6 + FIELD + 1) | (uv[:, 1] > 6 + FIELD + 1)  # beyond Phi's receptive field
    assert far.any() and (~far).any()
    assert torch.equal(disp[far], torch.zeros_like(disp[far]))
    assert (disp[~far].abs().sum(1) > 0).any()
    global_model, _ = build(TINY.replace(local_sampling=False))
    randomize_event_branch(global_model)
    _, _, disp_global = global_model.control_motion(0.25, emap, None)
    assert (disp_global.abs().sum(1) > 0).all()
    del t, trans_ev


def test_deform_validates_its_inputs():
    model, _ = build()
    t = tiny_scene.T0 + 50_000
    with pytest.raises(InvalidInputError, match="event_map"):
        model.deform(t, np.ones((3, 3), np.float32))
    bad = np.ones((tiny_scene.H, tiny_scene.W), np.float32)
    bad[0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        model.deform(t, bad)
    with pytest.raises(InvalidInputError, match="before the first anchor"):
        model.deform(tiny_scene.T0 - 10)
    with pytest.raises(InvalidInputError):
        model.deform(t, np.ones((tiny_scene.H, tiny_scene.W), np.float32), np.full((4, 4), np.nan))


def test_render_shapes_and_range():
    model, data = build()
    state = model.deform(tiny_scene.T0)
    assert torch.get_num_threads() == 1  # the skinning kernel runs on torch's threads and leaves them
    for fast in (False, True):
        img = model.render(state, np.eye(4), model.meta.intrinsics, fast=fast)
        assert img.shape == (tiny_scene.H, tiny_scene.W, 3) and img.dtype == np.float32
        assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
    assert torch.get_num_threads() == 1  # numba's OpenMP must not leave torch's thread count changed
    # the caller's thread count reaches the rasterizer (a count it cannot run is refused there)
    assert np.array_equal(model.render(state, np.eye(4), model.meta.intrinsics, threads=1), img)
    with pytest.raises(InvalidInputError, match="threads"):
        model.render(state, np.eye(4), model.meta.intrinsics, threads=10_000)
    assert torch.get_num_threads() == 1
    small = model.meta.intrinsics.scaled(24, 16)
    assert model.render(state, np.eye(4), small, background=1.0).shape == (16, 24, 3)
    # the untrained model already looks like its first anchor (pixels lifted at their colours)
    ref = model.render(state, np.eye(4), model.meta.intrinsics, fast=False)
    err = np.abs(ref - data.anchor_images[0] / 255.0).mean()
    assert err < 0.2


def test_checkpoint_round_trip_renders_identically(tmp_path):
    model, _ = build()
    randomize_event_branch(model)
    path = tmp_path / "scene.ckpt"
    save_checkpoint(model, path)
    loaded = load_checkpoint(path)
    assert not loaded.training
    assert loaded.meta.t_start_us == model.meta.t_start_us and loaded.meta.t_end_us == model.meta.t_end_us
    assert np.array_equal(loaded.meta.anchors_us, model.meta.anchors_us)
    assert loaded.meta.intrinsics == model.meta.intrinsics and loaded.meta.config == model.meta.config
    t = tiny_scene.T0 + 130_000
    assert np.array_equal(loaded.meta.trajectory.at(t), model.meta.trajectory.at(t))  # static: one pose
    emap = np.zeros((tiny_scene.H, tiny_scene.W), np.float32)
    emap[12:22, 20:30] = -2
    a, b = model.deform(t, emap), loaded.deform(t, emap)
    assert states_equal(a, b)
    for fast in (False, True):
        assert np.array_equal(model.render(a, np.eye(4), model.meta.intrinsics, fast=fast),
                              loaded.render(b, np.eye(4), loaded.meta.intrinsics, fast=fast))
    assert path.stat().st_size < 1_000_000
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_checkpoints_get_the_usual_permissions(tmp_path, umask):
    model, _ = build()
    old = os.umask(umask)
    try:
        save_checkpoint(model, tmp_path / "scene.ckpt")
    finally:
        os.umask(old)
    assert (tmp_path / "scene.ckpt").stat().st_mode & 0o777 == 0o666 & ~umask


def test_checkpoint_errors(tmp_path):
    model, _ = build()
    path = tmp_path / "scene.ckpt"
    save_checkpoint(model, path)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.ckpt")
    blob = path.read_bytes()
    (tmp_path / "cut.ckpt").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(tmp_path / "cut.ckpt")
    (tmp_path / "noise.ckpt").write_bytes(b"\x00garbage" * 100)
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "noise.ckpt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.ckpt")
    with pytest.raises(CheckpointError, match="not an EdMCGS checkpoint"):
        load_checkpoint(tmp_path / "foreign.ckpt")
    payload = read_checkpoint(path)
    assert payload["format"] == FORMAT
    payload["version"] = VERSION + 1
    torch.save(payload, tmp_path / "newer.ckpt")
    with pytest.raises(CheckpointError, match="newer"):
        load_checkpoint(tmp_path / "newer.ckpt")
    payload["version"] = VERSION
    payload["state_dict"]["gaussians.means"] = payload["state_dict"]["gaussians.means"][:5]
    torch.save(payload, tmp_path / "inconsistent.ckpt")
    with pytest.raises(CheckpointError, match="checksum"):  # edited after writing: the checksum says so
        load_checkpoint(tmp_path / "inconsistent.ckpt")
    payload["checksum"] = checksum(payload)  # written that way: the shape check says so
    torch.save(payload, tmp_path / "inconsistent.ckpt")
    with pytest.raises(CheckpointError, match="shape"):
        load_checkpoint(tmp_path / "inconsistent.ckpt")


def _mean_loss(trainer, steps):
    return float(np.mean([trainer.train_step()["photo"] for _ in range(steps)]))


def test_a_few_training_steps_lower_the_loss():
    model, data = build(TINY.replace(densify_from=0.9))
    trainer = Trainer(model, data, progress=False)
    first = _mean_loss(trainer, 4)
    for _ in range(8):
        trainer.train_step()
    assert _mean_loss(trainer, 4) < 0.8 * first


@pytest.mark.parametrize("switches", [dict(events=False), dict(markov=False), dict(local_sampling=False),
                                      dict(tli=False)])
def test_every_ablation_trains_on_the_same_code_path(switches):
    cfg = TINY.replace(iterations=6, **switches)
    model, data = build(cfg)
    assert (model.encoder is not None) == cfg.has_event_branch
    trainer = Trainer(model, data, progress=False)
    for _ in range(6):
        out = trainer.train_step()
        assert all(math.isfinite(v) for v in out.values())
    assert ("event" in out) == cfg.events
    assert ("tli" in out) == cfg.tli


def test_stiff_motion_trains_without_nan_or_inf():
    # The square crosses half the image (24 px) between two anchors; every window is full of events.
    cfg = TINY.replace(iterations=24, densify_from=0.1, densify_every=5, event_warmup=(0.0, 0.05))
    model, data = build(cfg, anchors_ms=(0, 100), held_ms=(50,), x0=2.0, x1=26.0, span_us=100_000)
    trainer = Trainer(model, data, progress=False)
    for _ in range(cfg.iterations):
        out = trainer.train_step()
        assert all(math.isfinite(v) for v in out.values()), out
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), name
    state = model.deform(tiny_scene.T0 + 50_000, data.event_map(tiny_scene.T0, tiny_scene.T0 + 50_000))
    img = model.render(state, np.eye(4), model.meta.intrinsics)
    assert np.isfinite(img).all()


def test_the_event_branch_warms_in_by_its_learning_rate_and_moves_nothing_before():
    """Off before the warm-in (scale 0, no step), then unscaled while its learning rate ramps: an output
    scale ramped under Adam let the raw output grow while the scale was small, and the ramp multiplied it."""
    cfg = TINY.replace(iterations=20, densify_from=0.9, event_warmup=(0.25, 0.75))
    model, data = build(cfg)
    trainer = Trainer(model, data, progress=False)
    before = [p.detach().clone() for p in model.transition.parameters()]

    def event_lr():
        return next(g["lr"] for g in trainer.optimizer.param_groups if g["name"] == "event")

    for _ in range(5):  # progress 0 .. 0.2: off
        trainer.train_step()
        assert float(model.event_scale) == 0.0 and event_lr() == 0.0
    assert all(torch.equal(a, b) for a, b in zip(before, model.transition.parameters(), strict=True))
    lrs = []
    for _ in range(10):  # progress 0.25 .. 0.7: the learning rate ramps, the output is not scaled
        trainer.train_step()
        assert float(model.event_scale) == 1.0
        lrs.append(event_lr())
    assert lrs[0] == 0.0 and bool(np.all(np.diff(lrs) > 0)) and lrs[-1] < cfg.lr_event
    assert not all(torch.equal(a, b) for a, b in zip(before, model.transition.parameters(), strict=True))


def test_resume_continues_where_it_stopped(tmp_path):
    cfg = TINY.replace(iterations=12, checkpoint_every=6, densify_from=0.9)
    model, data = build(cfg)
    trainer = Trainer(model, data, progress=False)
    for _ in range(3):
        trainer.train_step()
    path = tmp_path / "run.ckpt"
    save_checkpoint(trainer.model, path, train_state=trainer.train_state())
    resumed = Trainer(load_checkpoint(path), data, progress=False)
    resumed.load_train_state(read_checkpoint(path)["train_state"])
    assert resumed.step == 3
    a, b = trainer.train_step(), resumed.train_step()
    assert a.keys() == b.keys()
    assert all(math.isclose(a[k], b[k], rel_tol=1e-4, abs_tol=1e-6) for k in a)


def test_training_below_the_ssim_window_size():
    # 48x32 at a quarter: 12x8 px renders, smaller than SSIM's 11x11 window.
    model, data = build(TINY.replace(train_scale=0.25, iterations=4))
    trainer = Trainer(model, data, progress=False)
    assert (trainer.intr.width, trainer.intr.height) == (12, 8)
    for _ in range(4):
        out = trainer.train_step()
        assert all(math.isfinite(v) for v in out.values()), out


def test_history_seconds_leave_evaluation_off_the_clock():
    cfg = TINY.replace(iterations=6, eval_every=2, densify_from=0.9)
    model, data = build(cfg)
    now = [0.0]

    def clock():  # every reading one second later
        now[0] += 1.0
        return now[0]

    trainer = Trainer(model, data, progress=False, clock=clock)

    def slow_evaluate(frames=None):
        now[0] += 100.0  # an evaluation costs 100 s of wall clock
        return {"psnr": 20.0, "ssim": 0.5, "frames": 1}

    trainer.evaluate = slow_evaluate
    history = trainer.fit()
    assert [h["step"] for h in history] == [2, 4, 6]
    assert [h["seconds"] for h in history] == [2.0, 4.0, 6.0]  # one second per step, none for evaluations
