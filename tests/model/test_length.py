"""Training whose cost follows the recording: the schedule per anchor window, the event sums made per gap
on demand, and a step of a model drawn in anchor windows working on its windows alone."""

from __future__ import annotations

import numpy as np
import torch

from edmcgs.model.config import preset
from edmcgs.model.data import EventGrid
from edmcgs.model.motion import gaussians as gaussians_module
from edmcgs.model.motion.row_grad import at_rows, gather_rows
from edmcgs.model.motion.windows import WINDOWS_KEPT, WindowIndex
from edmcgs.model.train.row_adam import RowAdam, select_rows
from edmcgs.model.train.trainer import Trainer
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


def test_row_adam_is_torch_s_adam_paid_lazily_whatever_rows_wait_and_for_how_long():
    """Rows left out of a step wait, their momentum moves owed; paid (``catch_up`` of the rows a step
    draws, ``flush`` of all), the path is torch's Adam's with zero gradients there: with a learning rate
    changing every step, rows idle past the momentum's horizon, and a state saved and loaded midway; what a
    waiting row owes never exceeds ``reach``."""
    torch.manual_seed(0)
    start = torch.randn(40, 3)
    ours, theirs = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    row_adam = RowAdam([{"name": "means", "params": [ours], "lr": 0.1}], row_groups=("means",), eps=1e-15)
    adam = torch.optim.Adam([theirs], lr=0.1, eps=1e-15)
    generator = torch.Generator().manual_seed(1)
    for step in range(400):
        for optimizer in (row_adam, adam):
            optimizer.param_groups[0]["lr"] = 0.1 * 0.99 ** step
        rows = None if step == 0 else torch.unique(torch.randint(0, 40, (3,), generator=generator))
        if step > 100:  # rows 30 to 39 idle for 300 steps: past the 264 the owed moves are summed over
            rows = rows[rows < 30] if len(rows[rows < 30]) else torch.tensor([0])
        grad = torch.randn(40, 3, generator=generator)
        if rows is not None:
            grad[~torch.isin(torch.arange(40), rows)] = 0.0
        if step == 80:  # a train state saved and loaded: the owed moves survive it
            saved = row_adam.state_dict()
            row_adam = RowAdam([{"name": "means", "params": [ours], "lr": 0.1}], row_groups=("means",),
                               eps=1e-15)
            row_adam.load_state_dict(saved)
            assert row_adam.state[ours]["row_step"].dtype == torch.long
            assert row_adam.state[ours]["owed"].dtype == torch.float64
            assert row_adam.state[ours]["step"] == 80
        # what any waiting row still owes stays within the bound the view cull allows for (reach)
        owed = (theirs.detach() - ours.detach()).abs().max()
        assert owed <= row_adam.reach(ours) * (1 + 1e-5) + 1e-7 and row_adam.reach(ours) < 100 * 0.1
        row_adam.catch_up(rows)
        if rows is not None:  # the rows a step reads are current before it
            torch.testing.assert_close(ours.detach()[rows], theirs.detach()[rows], rtol=1e-5, atol=1e-5)
        ours.grad, theirs.grad = grad.clone(), grad.clone()
        row_adam.rows = rows
        row_adam.step(), adam.step()
    waiting = ours.detach().clone()
    assert (waiting[30:] - theirs.detach()[30:]).abs().max() > 1e-3  # the idle rows' moves still owed
    row_adam.flush()
    torch.testing.assert_close(ours.detach(), theirs.detach(), rtol=1e-5, atol=1e-5)
    assert (theirs.detach() - start).abs().max() > 1.0
    for key in ("exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(row_adam.state[ours][key], adam.state[theirs][key], rtol=1e-4, atol=1e-9)
    assert row_adam.state[ours]["row_step"].eq(400).all()


def test_density_control_keeps_the_owed_moves_of_the_rows_it_keeps():
    torch.manual_seed(0)
    means = torch.nn.Parameter(torch.randn(6, 3))
    row_adam = RowAdam([{"name": "means", "params": [means], "lr": 0.1}], row_groups=("means",), eps=1e-15)
    for rows in (torch.arange(6), torch.tensor([1, 2])):
        row_adam.rows = rows
        means.grad = torch.ones(6, 3)
        row_adam.step()
    state = row_adam.state[means]
    keep = torch.tensor([True, False, True, True, True, False])
    select_rows(state, keep, added=2)
    assert state["row_step"].tolist() == [1, 2, 1, 1, 2, 2]  # rows 0, 3, 4 owe step 2; the new are current
    assert state["exp_avg"].shape == (6, 3) and not state["exp_avg"][4:].any()


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


def test_a_windowed_step_moves_the_gaussians_of_the_windows_it_draws_alone():
    """A step moves the Gaussians of the windows it draws (caught up first with the momentum they owe);
    the others wait until drawn again, or until the model is read whole (``flush``)."""
    model, data = build(WINDOWED.replace(iterations=8, lr_means=0.05))
    trainer = Trainer(model, data, progress=False)
    birth = model.gaussians.birth
    owed_seen = False
    for _ in range(8):
        before = {name: getattr(model.gaussians, name).detach().clone()
                  for name in ("means", "opacity_logits", "features")}
        state = trainer.rng.bit_generator.state
        n = trainer._draw(trainer.anchor_shard)  # the draws the step will make
        gap = trainer._draw(trainer.gap_shard)
        trainer.rng.bit_generator.state = state
        assert np.isfinite(trainer.train_step()["loss"])
        untouched = ~torch.isin(birth, torch.tensor([n, gap]))
        for name, value in before.items():
            assert torch.equal(getattr(model.gaussians, name).detach()[untouched], value[untouched]), name
        assert not torch.equal(model.gaussians.means.detach()[birth == n], before["means"][birth == n])
        waiting = model.gaussians.means.detach().clone()
        trainer.settle()
        moved = (model.gaussians.means.detach() != waiting).any(1)
        assert not moved[~untouched].any()  # the drawn windows were current
        owed_seen |= bool(moved[untouched].any())  # a window drawn before, idle now: its momentum paid
    assert owed_seen


def test_a_windowed_run_takes_its_steps_per_window():
    cfg = WINDOWED.replace(steps_per_window=3, iterations=1)
    model, data = build(cfg)
    trainer = Trainer(model, data, progress=False)
    assert trainer.total_steps == 6  # three anchors: two spans
    trainer.fit()
    assert trainer.step == 6


def test_a_window_index_keeps_the_rows_of_the_windows_used_last():
    """Each window's rows hold a copy of the static set's indices: an index keeps ``WINDOWS_KEPT`` windows'
    (the last used), not every window's, and a window built again has the same rows."""
    gen = torch.Generator().manual_seed(0)
    birth = torch.randint(-1, 30, (3000,), generator=gen)
    control_birth = torch.arange(30).repeat_interleave(4)
    bind = torch.randint(0, 120, (3000, 4), generator=gen)
    graph = torch.randint(0, 120, (120, 3), generator=gen)
    index = WindowIndex(key=("k",))
    first = index.rows(0, birth, control_birth, bind, graph)
    assert index.rows(0, birth, control_birth, bind, graph) is first  # kept while used
    for w in range(30):
        index.rows(w, birth, control_birth, bind, graph)
    assert sorted(index._rows) == list(range(30 - WINDOWS_KEPT, 30))
    again = index.rows(0, birth, control_birth, bind, graph)
    assert again is not first
    for name in ("gaussians", "control", "bind", "graph", "drawn", "skinned"):
        assert torch.equal(getattr(again, name), getattr(first, name))
    assert again.own == first.own
