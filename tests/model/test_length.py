"""Training whose cost follows the recording: the schedule per anchor window, the event sums made per gap
on demand, and a step of a model drawn in anchor windows working on its windows alone."""

from __future__ import annotations

from collections import deque

import numpy as np
import torch

from edmcgs.model.config import preset
from edmcgs.model.data import EventGrid
from edmcgs.model.motion import gaussians as gaussians_module
from edmcgs.model.motion.row_grad import at_rows, gather_rows
from edmcgs.model.train.row_adam import RowAdam
from edmcgs.model.train.trainer import MOMENTUM_STEPS, Trainer
from tests.support import tiny_scene
from tests.support.models import TINY, build, one_torch_thread  # noqa: F401

WINDOWED = TINY.replace(bg_layer=True, anchor_windows=True, event_act="leaky", dynamic_threshold=0.06,
                        lambda_next=1.0, init_opacity=0.7, anchored_pairs=0.5, densify_until=0.0)


def test_the_real_preset_takes_steps_points_and_gaussians_per_anchor_window():
    real = preset("real")
    # 3 s at 5 fps: 16 anchors, 15 spans: the 1500 steps, 512 points and 60000 Gaussians it always had
    assert (real.total_steps(16), real.control_points(16), real.initial_points(16)) == (1500, 512, 60000)
    assert (real.total_steps(301), real.control_points(301), real.initial_points(301)) == \
        (30000, 9632, 1_128_750)
    # shorter: never below those (a 2.4 s clip trains as it always did)
    assert (real.total_steps(12), real.control_points(12), real.initial_points(12)) == (1500, 512, 60000)
    assert real.replace(iterations=1).total_steps(1) == 100  # one anchor: one span, to the recording's end
    demo = preset("demo")  # no steps per window: a fixed total, whatever the length
    assert (demo.total_steps(16), demo.total_steps(301)) == (1500, 1500)
    assert (demo.control_points(301), demo.initial_points(301)) == (demo.num_control_points, demo.init_points)
    fixed = real.with_overrides(["iterations=700"])  # a total given: fixed
    assert (fixed.steps_per_window, fixed.total_steps(301)) == (0, 700)
    both = real.with_overrides(["iterations=700", "steps_per_window=5"])
    assert both.total_steps(301) == 1500
    unwindowed = real.replace(anchor_windows=False)
    assert unwindowed.control_points(301) == 512 and unwindowed.initial_points(301) == 60000


def test_the_moving_preset_takes_steps_points_and_lifted_gaussians_per_anchor_window():
    moving = preset("moving")
    # street3d's 4 s at 5 fps (21 anchors): the 1500 steps, 512 points, 60000 lifted and 150000 at most
    # that it was measured with
    assert (moving.total_steps(21), moving.control_points(21), moving.initial_points(21),
            moving.gaussian_cap(21)) == (1500, 512, 60000, 150000)
    # a minute: the same per window; the static set keeps its own budget beside the movers'
    assert (moving.total_steps(301), moving.control_points(301), moving.initial_points(301),
            moving.gaussian_cap(301)) == (22500, 7224, 859_957, 949_957)
    assert preset("real").gaussian_cap(301) == 60000 + 1_128_750 - 60000
    assert preset("demo").gaussian_cap(301) == preset("demo").max_gaussians


def test_a_new_model_gets_points_per_window():
    model, _ = build(WINDOWED.replace(control_points_per_window=5, num_control_points=12))
    assert model.control.num_points == 15  # three anchors
    assert torch.bincount(model.control.birth, minlength=3).tolist() == [5, 5, 5]


def _reference(data, substeps: int) -> tuple[np.ndarray, torch.Tensor]:
    """Every gap's running sums, made up front as training made them before sums were made on demand."""
    grid = EventGrid.build(data, substeps)
    w, h = data.event_size
    cum = torch.zeros(grid.num_gaps, substeps + 1, h, w)
    for n in range(grid.num_gaps):
        for j in range(substeps):
            window = np.asarray(data.event_map(int(grid.times[n, j]), int(grid.times[n, j + 1])), np.float32)
            cum[n, j + 1] = cum[n, j] + torch.from_numpy(window)
    return grid.times, cum


def test_event_sums_made_on_demand_equal_the_sums_made_up_front():
    data = tiny_scene.data(anchors_ms=(0, 40, 100, 130, 200))
    times, reference = _reference(data, 5)
    w, h = data.event_size
    one_gap = 6 * h * w * 4
    # a cache of one gap, of two (least recently used out), of all: the same sums, made again when gone
    for gaps, made in ((1, 9), (2, 8), (100, 4)):
        grid = EventGrid.build(data, 5, cache_bytes=gaps * one_gap)
        np.testing.assert_array_equal(grid.times, times)
        for gap in [2, 0, 2, 3, 1, 0, 3, 3, 1, 2]:
            assert torch.equal(grid.cumulative(gap), reference[gap])
        assert (grid.capacity, grid.made) == (gaps, made)


def test_row_adam_steps_the_rows_given_as_adam_does_and_leaves_the_rest():
    torch.manual_seed(0)
    rows = torch.tensor([1, 4, 5])
    start = torch.randn(7, 3)
    ours = torch.nn.Parameter(start.clone())
    theirs = torch.nn.Parameter(start.clone())
    sub = torch.nn.Parameter(start[rows].clone())
    row_adam = RowAdam([{"name": "means", "params": [ours], "lr": 0.1}], row_groups=("means",), eps=1e-15)
    adam = torch.optim.Adam([theirs], lr=0.1, eps=1e-15)
    adam_sub = torch.optim.Adam([sub], lr=0.1, eps=1e-15)
    for step in range(5):
        grad = torch.randn(7, 3)
        if step:
            grad[[0, 2, 3, 6]] = 0.0  # the rows no drawn window holds
        for p, g in ((ours, grad), (theirs, grad), (sub, grad[rows])):
            p.grad = g.clone()
        row_adam.rows = None if step == 0 else rows  # first every row, as torch's Adam
        row_adam.step(), adam.step()
        if step == 0:
            torch.testing.assert_close(ours.detach(), theirs.detach(), rtol=0, atol=0)
            adam_sub = torch.optim.Adam([sub], lr=0.1, eps=1e-15)
            with torch.no_grad():
                sub.copy_(ours[rows])
            moved = ours.detach().clone()
            adam_sub.state[sub] = {k: (v[rows].clone() if v.dim() else v.clone())
                                   for k, v in row_adam.state[ours].items()}
            continue
        adam_sub.step()
    torch.testing.assert_close(ours.detach()[rows], sub.detach(), rtol=1e-6, atol=1e-7)
    others = torch.tensor([0, 2, 3, 6])
    assert torch.equal(ours.detach()[others], moved[others])  # no momentum drift outside the rows
    assert not torch.equal(theirs.detach()[others], moved[others])  # as torch's Adam would drift them


def test_a_row_gather_gives_indexing_s_values_and_a_sparse_gradient_of_its_rows_alone():
    torch.manual_seed(0)
    source = torch.nn.Parameter(torch.randn(9, 2, 3))
    dense = torch.nn.Parameter(source.detach().clone())
    rows_a, rows_b = torch.tensor([1, 4, 5]), torch.tensor([4, 8])
    weight = torch.randn(3, 2, 3)
    for p, gather in ((source, gather_rows), (dense, lambda s, r: s[r])):
        a, b = gather(p, rows_a), gather(p, rows_b)
        ((a * weight).sum() + b.pow(2).sum()).backward()
    torch.testing.assert_close(gather_rows(source, rows_a), dense[rows_a], rtol=0, atol=0)
    assert source.grad.is_sparse and not dense.grad.is_sparse
    assert sorted(source.grad.coalesce().indices()[0].tolist()) == [1, 4, 5, 8]  # row 4 twice, summed
    torch.testing.assert_close(source.grad.to_dense(), dense.grad, rtol=0, atol=1e-7)
    rows = torch.tensor([0, 1, 4, 5, 8])  # a row beyond the gradient's reads zero
    torch.testing.assert_close(at_rows(source.grad, rows), dense.grad[rows], rtol=0, atol=1e-7)
    torch.testing.assert_close(at_rows(dense.grad, rows), dense.grad[rows], rtol=0, atol=0)
    with torch.no_grad():  # no graph, no sparse gradient: plain indexing
        assert gather_rows(source, rows_a).grad_fn is None


def test_windowed_steps_move_the_model_as_dense_gradients_would(monkeypatch):
    """The sparse row gradients are a cost, not a change: the same steps with ``p[rows]``'s dense
    gradients give the same model."""
    def trained(gather) -> dict[str, torch.Tensor]:
        monkeypatch.setattr(gaussians_module, "gather_rows", gather)
        torch.manual_seed(0)
        model, data = build(WINDOWED.replace(iterations=6))
        trainer = Trainer(model, data, progress=False)
        assert model.windowed
        for _ in range(6):
            assert np.isfinite(trainer.train_step()["loss"])
        assert model.gaussians.means.grad.is_sparse == (gather is gather_rows)
        return {k: v.detach().clone() for k, v in model.state_dict().items()}

    sparse, dense = trained(gather_rows), trained(lambda s, r: s[r])
    assert sparse.keys() == dense.keys()
    for name in sparse:
        torch.testing.assert_close(sparse[name], dense[name], rtol=1e-5, atol=1e-6, msg=name)


@torch.no_grad()
def test_a_window_state_is_the_full_state_of_its_gaussians():
    model, data = build(WINDOWED)
    t = int(data.held_out_t_us[0])
    emap = torch.as_tensor(data.event_map(model.tau(t), t))
    w2c = torch.eye(4)
    window = model.window(t)
    full = model.state_from_motion(*model.control_motion(model.meta.normalized_time(t), emap, w2c,
                                                         since=model.meta.normalized_time(model.tau(t)))[:2],
                                   window)
    rows = model.window_rows(window)
    local = model.window_state(*model.control_motion(model.meta.normalized_time(t), emap, w2c,
                                                      window=window)[:2], window)
    for name in ("means", "quats", "scales", "opacities", "colors"):
        torch.testing.assert_close(getattr(local, name), getattr(full, name)[rows.gaussians], rtol=1e-5,
                                   atol=1e-6)
    assert bool((full.opacities[rows.gaussians] > 0).all())
    others = torch.ones(len(model.gaussians), dtype=torch.bool)
    others[rows.gaussians] = False
    assert float(full.opacities[others].abs().max()) == 0.0  # nothing else is drawn there


def test_a_windowed_step_moves_the_gaussians_of_the_windows_drawn_lately_alone():
    """The windows drawn in the last steps move (the step's by their gradients, the earlier ones' by Adam's
    momentum); the others wait. A run remembers MOMENTUM_STEPS steps; here two."""
    model, data = build(WINDOWED.replace(iterations=8, lr_means=0.05))
    trainer = Trainer(model, data, progress=False)
    assert trainer.recent.maxlen == MOMENTUM_STEPS == 66
    trainer.recent = deque(maxlen=2)
    birth = model.gaussians.birth
    momentum_seen = False
    for _ in range(8):
        drawn_before = {name: getattr(model.gaussians, name).detach().clone()
                        for name in ("means", "opacity_logits", "features")}
        state = trainer.rng.bit_generator.state
        n = trainer._draw(trainer.anchor_shard)  # the draws the step will make
        trainer.rng.bit_generator.state = state
        terms = trainer.train_step()
        assert np.isfinite(terms["loss"])
        lately = torch.tensor(sorted({w for step in trainer.recent for w in step}))
        untouched = ~torch.isin(birth, lately)
        for name, before in drawn_before.items():
            after = getattr(model.gaussians, name).detach()
            assert torch.equal(after[untouched], before[untouched]), name
        assert not torch.equal(model.gaussians.means.detach()[birth == n], drawn_before["means"][birth == n])
        before = trainer.recent[0][0] if len(trainer.recent) == 2 else None  # the anchor the step before drew
        if before is not None and before not in trainer.recent[-1]:
            momentum_seen = True  # not drawn now: moved by its momentum alone
            moved = model.gaussians.means.detach()[birth == before]
            assert not torch.equal(moved, drawn_before["means"][birth == before])
    assert momentum_seen


def test_a_windowed_run_takes_its_steps_per_window():
    cfg = WINDOWED.replace(steps_per_window=3, iterations=1)
    model, data = build(cfg)
    trainer = Trainer(model, data, progress=False)
    assert trainer.total_steps == 6  # three anchors: two spans
    trainer.fit()
    assert trainer.step == 6
