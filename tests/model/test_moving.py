"""The ``moving`` preset: a static set of Gaussians on 3D points, drawn at every time and never moved, and
what moves lifted from the anchor pixels the static set does not explain into their anchor windows."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import Tensor

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import project, world_to_camera
from edmcgs.model.checkpoint import load_checkpoint, save_checkpoint
from edmcgs.model.config import preset
from edmcgs.model.dynamic import ANCHOR_PRIORS
from edmcgs.model.motion.gaussians import STATIC
from edmcgs.model.train.trainer import Trainer
from edmcgs.pipeline import default_preset, new_model, training_data
from edmcgs.synth.esim import AdaptiveSampling
from edmcgs.synth.street3d import StreetScene
from edmcgs.synth.street3d_build import Street3dConfig, build_street3d
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, one_torch_thread, perturb_prior  # noqa: F401

SMALL = preset("moving").replace(
    num_control_points=32, deform_width=32, deform_depth=2, substeps=4, max_pair_steps=4, eval_every=0,
    checkpoint_every=0, densify_every=3, event_warmup=(0.0, 0.2), init_points=2000,
    steps_per_window=0, control_points_per_window=0, init_points_per_window=0)  # a fixed, tiny schedule


def _true_points(rec, every: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """3D points of the street without its cars, from the ray caster's depth at the anchors (every
    ``every``-th pixel), in their colours: what structure from motion would give, exactly."""
    scene = StreetScene(rec.width, rec.height, seed=int(rec.metadata["seed"]))
    k = rec.intrinsics
    xyz, grey = [], []
    for pose, image in zip(rec.anchors.poses, rec.anchors.images, strict=True):
        frame = scene.static_frame(pose)
        v, u = np.mgrid[0:rec.height:every, 0:rec.width:every]
        z = frame.depth[v, u]
        ok = np.isfinite(z)
        cam = np.stack([(u[ok] - k[2]) / k[0] * z[ok], (v[ok] - k[3]) / k[1] * z[ok], z[ok]], 1)
        xyz.append(cam @ pose[:3, :3].T + pose[:3, 3])
        grey.append(image[v[ok], u[ok]])
    return np.concatenate(xyz), np.concatenate(grey)


@pytest.fixture(scope="module")
def street():
    """A tiny street3d (173x130, 0.4 s: 3 anchors) with the true points of its still street."""
    rec = build_street3d(Street3dConfig(width=173, height=130, duration_s=0.4, sampling=AdaptiveSampling(
        dt_max_us=4000, dt_min_us=2000, max_delta=2.0)), progress=False)
    xyz, colors = _true_points(rec)
    return replace(rec, points_xyz=xyz, points_colors=colors)


def test_the_static_set_starts_on_the_points_at_their_depths_and_never_moves(street):
    data = training_data(street)
    assert data.points_xyz.shape == street.points_xyz.shape  # carried into the training data
    model = new_model(data, SMALL)
    g = model.gaussians
    assert bool((g.birth == STATIC).all()) and len(g) == len(street.points_xyz)
    np.testing.assert_allclose(g.means.detach().numpy(), street.points_xyz, rtol=0, atol=1e-4)
    torch.testing.assert_close(g.colors().detach()[:, 0], torch.from_numpy(
        street.points_colors[:, 0] / 255.0).float().clamp(0.02, 0.98), atol=1e-4, rtol=0)
    # the render's depth where a point projects is the point's depth: the Gaussians sit where the points are
    pose, intr = data.anchor_poses[1], data.intrinsics
    state = model.deform(int(data.anchors_t_us[1]))
    depth, alpha = model.render_depth_alpha(state, pose, intr)
    uv, z = project(street.points_xyz, world_to_camera(pose), intr)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < intr.width - 1) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < intr.height - 1)
    u, v = np.rint(uv[inside]).astype(int).T
    seen = alpha[v, u] > 0.05  # (each starts at 3DGS's opacity 0.1: a point alone is faint)
    assert seen.mean() > 0.8
    assert np.median(np.abs(depth[v, u][seen] / z[inside][seen] - 1)) < 0.05
    # never moved, whatever the prior and the events do: at any time, and through the training path
    randomize_event_branch(model)
    with torch.no_grad():
        for p in model.prior.parameters():
            p.add_(torch.randn_like(p) * 0.3)
    t = int(data.held_out_t_us[2])
    moved = model.deform(t, data.event_map(model.tau(t), t))
    torch.testing.assert_close(moved.means, g.means.detach(), rtol=0, atol=0)
    trained = model.state_at(0.7, window=1)
    torch.testing.assert_close(trained.means, g.means, rtol=0, atol=0)


def test_the_static_set_needs_points():
    with pytest.raises(InvalidInputError, match="--poses auto"):
        new_model(tiny_scene.data(), SMALL)
    with pytest.raises(InvalidInputError, match="anchor_windows"):
        SMALL.replace(anchor_windows=False)


def _square_on_a_wall(**changes):
    """A grey wall (the background colour) that the static set explains, and a bright 8x10 square that
    only anchor 1 sees (80 pixels to lift); the data and SMALL with ``changes``."""
    data = tiny_scene.data()
    data.anchor_images[:] = 128
    data.anchor_images[1, 10:18, 20:30] = 250
    points = np.random.default_rng(0).uniform([-0.5, -0.3, 1.8], [0.5, 0.3, 2.2], (64, 3))
    data.points_xyz, data.points_colors = points, np.full((64, 3), 128, np.uint8)
    return data, SMALL.replace(bg_layer=False, background=(128 / 255,) * 3, dynamic_threshold=0.1,
                               densify_every=100, **changes)


def test_the_lift_puts_what_the_static_set_misses_into_its_window():
    # the square's pixels, and only they, are lifted into window 1
    data, cfg = _square_on_a_wall(lift_at=0.5, iterations=4, init_points=10_000)
    model = new_model(data, cfg)
    trainer = Trainer(model, data, progress=False)
    trainer.train_step()
    assert not trainer.lifted and bool((model.gaussians.birth == STATIC).all())
    trainer.train_step()
    trainer.train_step()  # progress 0.5: lifted before this step
    assert trainer.lifted and trainer.lift_counts == [0, 80, 0]
    g = model.gaussians
    born = g.birth == 1
    assert int(born.sum()) == 80 and int((g.birth >= 0).sum()) == 80
    uv, _ = project(g.means.detach()[born].numpy(), world_to_camera(data.anchor_poses[1]), data.intrinsics)
    assert np.all((uv[:, 0] > 19.5) & (uv[:, 0] < 29.5) & (uv[:, 1] > 9.5) & (uv[:, 1] < 17.5))
    assert bool((model.control.birth == 1).all())  # the control points carry what moves
    # the static set is drawn in every window, the lifted square only in its own: a render's state holds
    # the Gaussians drawn, in the model's order
    static = int((g.birth == STATIC).sum())
    for window, rows in ((0, static), (1, len(g)), (2, static)):
        state = model.deform(int(data.anchors_t_us[window]))
        assert len(state.means) == rows and state.opacities.min() > 0
    np.testing.assert_array_equal(state.means.numpy(), g.means.detach()[g.birth == STATIC].numpy())
    # mid-gap, a render moves the control points its drawn Gaussians bind alone: the same Gaussians as the
    # differentiable path (every point, with gradients) to float32 rounding
    randomize_event_branch(model)
    perturb_prior(model)
    t = int(data.anchors_t_us[1]) + 40_000
    emap = data.event_map(int(data.anchors_t_us[1]), t)
    assert np.any(emap != 0)
    fast = model.deform(t, emap)
    w2c = torch.as_tensor(world_to_camera(model.meta.trajectory.at(t)), dtype=torch.float32)
    ref = model.state_at(model.meta.normalized_time(t), torch.as_tensor(emap), w2c, window=1)
    drawn = g.visible_in(1) > 0
    torch.testing.assert_close(model.window_rows(1).drawn, torch.nonzero(drawn)[:, 0])
    assert (fast.means - ref.means.detach()).abs().max() < 1e-5 * float(model.extent)
    assert (fast.quats - ref.quats.detach()).abs().max() < 1e-5
    # training's path (the window's control points, its rows and the static set alone) is the whole
    # model's, every point moved since the anchor, every row skinned, cut to the drawn rows
    since = model.meta.normalized_time(int(data.anchors_t_us[1]))
    trans, rot, _ = model.control_motion(model.meta.normalized_time(t), torch.as_tensor(emap), w2c,
                                         since=since)
    whole = model.state_from_motion(trans, rot, 1)
    assert (whole.means.detach()[drawn] - ref.means.detach()).abs().max() < 1e-5 * float(model.extent)
    assert (whole.quats.detach()[drawn] - ref.quats.detach()).abs().max() < 1e-5
    lifted = g.birth[drawn] == 1
    assert (fast.means[lifted] - g.means.detach()[g.birth == 1]).abs().max() > 1e-3  # the square moved


def test_the_moving_preset_trains_on_a_street_and_round_trips(street, tmp_path):
    data = training_data(street)
    cfg = SMALL.replace(iterations=6, lift_at=0.5, dynamic_threshold=0.08)
    model = new_model(data, cfg)
    trainer = Trainer(model, data, progress=False)
    terms, losses = {}, []
    for _ in range(cfg.iterations):
        terms.update(trainer.train_step())
        losses.append(terms["loss"])
    assert all(math.isfinite(v) for v in losses)  # before the lift too: windows with no points of their own
    assert trainer.lifted and sum(trainer.lift_counts) > 0
    assert {"photo", "event", "next"} <= set(terms) and all(math.isfinite(v) for v in terms.values())
    birth = model.gaussians.birth
    # a step moved the rows of the windows it drew and the static set, not the others' (lazy Adam)
    moved = torch.zeros(len(birth), dtype=torch.bool)
    moved[trainer.optimizer.rows] = True
    assert bool(moved[birth == STATIC].all()) and not bool(moved.all())
    assert bool((birth == STATIC).any()) and bool((birth >= 0).any())
    path = tmp_path / "m.ckpt"
    model.eval()
    save_checkpoint(model, path)
    loaded = load_checkpoint(path)
    assert torch.equal(loaded.gaussians.birth, birth)
    assert Trainer(loaded, data, progress=False).lifted  # training on from the file does not lift again
    t = int(data.held_out_t_us[1])
    emap = data.event_map(model.tau(t), t)
    pose = data.held_out_pose(1)
    np.testing.assert_array_equal(model.render(model.deform(t, emap), pose, data.intrinsics),
                                  loaded.render(loaded.deform(t, emap), pose, data.intrinsics))


def test_a_step_draws_the_static_rows_its_cameras_see_and_trains_as_if_it_drew_them_all(street, monkeypatch):
    """The view cull (``Trainer._rows_in_view``): a quarter of the static set put behind every camera is
    left out of every step, and the run goes where drawing the whole static set takes it (RowAdam pays
    the left-out rows' momentum when they are next read)."""
    data = training_data(street)
    cfg = SMALL.replace(iterations=8, lift_at=0.25, dynamic_threshold=0.08, densify_until=0.0)
    first = data.anchor_poses[0]
    runs = []
    for cull in (True, False):
        model = new_model(data, cfg)
        g = model.gaussians
        static = torch.nonzero(g.birth == STATIC)[:, 0]
        hidden = static[::4]
        behind = torch.as_tensor(first[:3, 3] - 20 * float(model.extent) * first[:3, 2], dtype=torch.float32)
        with torch.no_grad():
            g.means[hidden] = behind + 0.1 * g.means[hidden]
        trainer = Trainer(model, data, progress=False)
        if not cull:
            monkeypatch.setattr(trainer, "_rows_in_view", lambda cameras, m=model: {w: m.window_rows(w)
                                                                                     for w in cameras})
        left_out, losses = [], []
        for _ in range(cfg.iterations):
            losses.append(trainer.train_step()["loss"])
            drawn = torch.zeros(len(g), dtype=torch.bool)
            drawn[trainer.optimizer.rows] = True
            left_out.append(int((~drawn[static]).sum()))
        trainer.optimizer.flush()
        runs.append((model, trainer, left_out, losses))
    (culled, trainer, left_out, losses), (whole, _, none_left, whole_losses) = runs
    assert trainer.lifted and min(left_out) >= len(hidden) and max(none_left) == 0
    np.testing.assert_allclose(losses, whole_losses, rtol=1e-5)
    # Adam's early moves are about a learning rate whatever the gradient's size: float rounding of a
    # near-zero gradient can turn one, so the parameters agree to a fraction of a move
    lrs = {group["name"]: group["lr"] for group in trainer.optimizer.param_groups}
    for name in ("means", "quats", "log_scales", "opacity_logits", "features"):
        ours, theirs = getattr(culled.gaussians, name), getattr(whole.gaussians, name)
        torch.testing.assert_close(ours, theirs, rtol=0, atol=0.5 * cfg.iterations * lrs[name])
        torch.testing.assert_close(ours[hidden], theirs[hidden], rtol=1e-6, atol=1e-7)


def test_moving_preset_switches():
    cfg = preset("moving")
    assert cfg.static_set and cfg.anchor_windows and cfg.bg_layer and cfg.lambda_next > 0
    assert cfg.densify_until > cfg.densify_from  # the static set is densified, as in 3DGS
    for name in ("demo", "real", "paper"):
        assert not preset(name).static_set
    assert not TINY.static_set


def test_train_picks_the_moving_preset_for_a_translating_camera_with_points(street):
    assert default_preset(street)[0] == "moving" and "points" in default_preset(street)[1]
    assert default_preset(replace(street, points_xyz=None, points_colors=None))[0] == "demo"
    for said in ({"static": True}, {"rotation_only": True}):  # --poses auto found no translation
        assert default_preset(replace(street, metadata={**street.metadata, "poses": said}))[0] == "demo"


def test_the_prior_at_an_anchor_is_kept_for_its_gap_and_dropped_when_the_prior_changes(street):
    """A render's motion since its anchor reuses the prior at that anchor (the same for every query in the
    gap); a change of the prior's parameters (a learner's next step, a load) is never served stale."""
    model = new_model(training_data(street), SMALL)
    perturb_prior(model)

    def motion(t: float, since: float, *, grad: bool) -> Tensor:
        with torch.set_grad_enabled(grad):
            return model.control_motion(t, since=since)[0].detach()

    for t in (0.3, 0.4, 0.45):  # three queries in one gap: one prior at its anchor
        torch.testing.assert_close(motion(t, 0.25, grad=False), motion(t, 0.25, grad=True), rtol=0, atol=0)
    assert len(model._anchor_priors) == 1
    with torch.no_grad():
        for p in model.prior.parameters():
            p.mul_(1.5)
    torch.testing.assert_close(motion(0.3, 0.25, grad=False), motion(0.3, 0.25, grad=True), rtol=0, atol=0)
    for since in np.linspace(0.0, 0.9, ANCHOR_PRIORS + 3):  # the anchors kept are bounded
        motion(0.95, float(since), grad=False)
    assert len(model._anchor_priors) == ANCHOR_PRIORS


def test_drawn_plans_are_kept_within_their_byte_budget(street, monkeypatch):
    """The plans of the windows a viewer scrubs through stay built while they fit DRAWN_PLANS_BYTES; past
    it, the oldest go, down to DRAWN_PLANS."""
    from edmcgs.model import dynamic

    model = new_model(training_data(street), SMALL)
    windows = range(len(model.meta.anchors_us))
    first = [model.drawn_plan(w) for w in windows]
    assert all(model.drawn_plan(w) is p for w, p in zip(windows, first, strict=True))  # none rebuilt
    assert len(model._drawn_plans) == len(windows)
    monkeypatch.setattr(dynamic, "DRAWN_PLANS_BYTES", first[0].nbytes)
    monkeypatch.setattr(dynamic, "DRAWN_PLANS", 1)
    model.drawn_plan(0)
    assert list(model._drawn_plans) == [(0, True)]


def test_the_lift_takes_its_gaussians_per_anchor_window():
    # 80 pixels to lift, 10 Gaussians allowed in all, 20 per window over three anchors: 60 lifted
    data, cfg = _square_on_a_wall(lift_at=0.0, iterations=2, init_points=10, init_points_per_window=20)
    trainer = Trainer(new_model(data, cfg), data, progress=False)
    trainer.train_step()
    assert trainer.lifted and trainer.lift_counts == [0, 60, 0]
