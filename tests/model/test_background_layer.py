"""The distant background layer, anchor windows and the leaky event encoder (config switches of the
``real`` preset): each off changes nothing, each on keeps the model's invariants."""

import math

import numpy as np
import pytest
import torch

from edmcgs.geometry import Intrinsics
from edmcgs.model.checkpoint import load_checkpoint, save_checkpoint
from edmcgs.model.config import preset
from edmcgs.model.motion.background import BackgroundLayer
from edmcgs.model.render.rasterize_fast import rasterize_fast
from edmcgs.model.train.density import GradientStats, densify_and_prune
from edmcgs.model.train.trainer import Trainer, write_history_csv
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, build, one_torch_thread  # noqa: F401

LAYERED = TINY.replace(bg_layer=True, anchor_windows=True, event_act="leaky", dynamic_threshold=0.06,
                       lambda_next=1.0, init_opacity=0.7)


def _yaw(deg: float) -> np.ndarray:
    a = math.radians(deg)
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
    return pose


def test_layer_off_renders_as_before():
    model, data = build()
    assert model.bg_layer is None and model.gaussians.birth is None
    t = int(data.held_out_t_us[0])
    state = model.deform(t, data.event_map(model.tau(t), t))
    image = model.render(state, np.eye(4), model.meta.intrinsics)
    arrays = [x.detach().numpy()
              for x in (state.means, state.quats, state.scales, state.opacities, state.colors)]
    direct = rasterize_fast(*arrays, np.eye(4, dtype=np.float32), model.meta.intrinsics,
                            background=np.zeros(3, np.float32)).image
    np.testing.assert_array_equal(image, np.clip(direct, 0, 1))


def test_reference_camera_reads_texels_and_median_drops_the_mover():
    model, _ = build(LAYERED)
    layer = model.bg_layer
    assert tuple(layer.texture.shape) == (3, tiny_scene.H, tiny_scene.W)
    view = layer.image(np.eye(3), model.meta.intrinsics)
    torch.testing.assert_close(view, layer.colors().permute(1, 2, 0))
    # The square is at three places in three anchors: the median is the plain background everywhere.
    expected = np.round(tiny_scene.image(tiny_scene.T0, size=0.0) * 255) / 255
    np.testing.assert_allclose(view.detach().numpy(), expected, atol=0.011)
    # Only the square's pixels get Gaussians: one on each (there are fewer than init_points).
    images = np.stack([np.round(tiny_scene.image(int(t)) * 255) / 255 for t in model.meta.anchors_us])
    differs = int((np.abs(images - expected).max(-1) > LAYERED.dynamic_threshold).sum())
    assert 0 < differs < TINY.init_points and len(model.gaussians) == differs


def test_panned_layer_covers_every_view_and_is_continuous():
    intr = Intrinsics(40.0, 40.0, 23.5, 15.5, 48, 32)
    rots = np.stack([np.eye(3), _yaw(5)[:3, :3]])
    layer = BackgroundLayer.covering(rots, intr, 1)
    assert layer.texture.shape[1] >= 32 and layer.texture.shape[2] > 48
    with torch.no_grad():
        layer.texture.copy_(torch.randn(layer.texture.shape, generator=torch.Generator().manual_seed(0)))
    turned = layer.image(rots[1], intr)
    assert torch.isfinite(turned).all() and turned.shape == (32, 48, 1)
    # A tiny turn reads (almost) the same texels.
    near = layer.image(_yaw(1e-4)[:3, :3], intr)
    torch.testing.assert_close(near, layer.image(np.eye(3), intr), atol=2e-3, rtol=0)


def test_median_fitted_in_bands_of_rows_equals_the_whole_texture_at_once():
    intr = Intrinsics(40.0, 40.0, 23.5, 15.5, 48, 32)
    rots = np.stack([np.eye(3), _yaw(5)[:3, :3], _yaw(-4)[:3, :3]])
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (3, 32, 48, 2), dtype=np.uint8)
    whole, banded = BackgroundLayer.covering(rots, intr, 2), BackgroundLayer.covering(rots, intr, 2)
    whole.fit_median(images, rots, intr, band_bytes=1 << 40)
    banded.fit_median(images, rots, intr, band_bytes=1)  # one texture row a band
    torch.testing.assert_close(banded.texture, whole.texture, rtol=0, atol=0)
    assert torch.isfinite(whole.texture).all()
    # Three still cameras: every texel is the median of its three pixels.
    still = np.stack([np.eye(3)] * 3)
    layer = BackgroundLayer.covering(still, intr, 2)
    layer.fit_median(images, still, intr, band_bytes=1)
    expected = np.clip(np.median(images, 0) / 255, 0.01, 0.99)
    np.testing.assert_allclose(layer.image(np.eye(3), intr).detach().numpy(), expected, atol=1e-5)


def test_a_turned_cameras_texels_are_where_its_rays_cross_the_reference_plane():
    """Each pixel's ray, turned into the reference camera and projected by it, lands on the texel the grid
    reads (float64 geometry here; the grid is applied in float32: within 1e-3 of a texel)."""
    intr = Intrinsics(300.0, 290.0, 172.5, 129.5, 346, 260)
    turn = _yaw(7.0)[:3, :3] @ np.array([[1, 0, 0], [0, math.cos(0.1), -math.sin(0.1)],
                                          [0, math.sin(0.1), math.cos(0.1)]])
    layer = BackgroundLayer.covering(np.stack([np.eye(3), turn]), intr, 1)
    grid = layer.texel_grid(turn, intr).numpy().astype(np.float64)
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float64)
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1) @ turn.T
    ref_u = intr.fx * rays[..., 0] / rays[..., 2] + intr.cx - layer.origin[0].item()
    ref_v = intr.fy * rays[..., 1] / rays[..., 2] + intr.cy - layer.origin[1].item()
    _, ht, wt = layer.texture.shape
    np.testing.assert_allclose((grid[..., 0] + 1) * (wt - 1) / 2, ref_u, rtol=0, atol=1e-3)
    np.testing.assert_allclose((grid[..., 1] + 1) * (ht - 1) / 2, ref_v, rtol=0, atol=1e-3)
    assert layer.texel_grid(torch.from_numpy(turn), intr).equal(layer.texel_grid(turn, intr))


@pytest.mark.parametrize("pose", [np.eye(4), _yaw(3.0)])
def test_fast_and_torch_renders_agree_with_the_layer(pose):
    model, data = build(LAYERED)
    randomize_event_branch(model)
    t = int(data.held_out_t_us[0])
    state = model.deform(t, data.event_map(model.tau(t), t))
    fast = model.render(state, pose, model.meta.intrinsics, fast=True)
    slow = model.render(state, pose, model.meta.intrinsics, fast=False)
    np.testing.assert_allclose(fast, slow, atol=2e-4)


def test_windows_draw_only_the_anchors_gaussians_in_their_canonical_pose():
    model, data = build(LAYERED)
    birth = model.gaussians.birth
    assert birth is not None and set(birth.tolist()) <= {0, 1, 2}
    for k, t in enumerate(data.anchors_t_us):
        state = model.deform(int(t))  # the window's Gaussians alone, in their order
        assert model.window(int(t)) == k
        torch.testing.assert_close(state.means, model.gaussians.means.detach()[birth == k])
        assert bool((state.opacities > 0).all())
    t = int(data.held_out_t_us[1])  # in gap 1
    assert model.window(t) == 1
    assert len(model.deform(t)) == int((birth == 1).sum())


def test_leaky_encoder_keeps_zero_events_exactly_zero():
    model, _ = build(LAYERED)
    randomize_event_branch(model)
    x = model.normalize_points(model.control.positions)
    feats = model.encoder(torch.zeros(1, 1, tiny_scene.H, tiny_scene.W))
    assert torch.equal(feats, torch.zeros_like(feats))
    codes = torch.zeros(model.control.num_points, 32)
    assert torch.equal(model.transition(x, codes), torch.zeros(model.control.num_points, 3))
    _, _, disp = model.control_motion(0.3, torch.zeros(tiny_scene.H, tiny_scene.W), torch.eye(4))
    assert disp is None
    # A negative input reaches the output through the leaky slope (a ReLU Phi would pass no gradient).
    h = model.encoder._act(torch.tensor([-1.0]))
    assert float(h) == pytest.approx(-0.1)


def test_checkpoint_round_trip_with_layer_and_windows(tmp_path):
    model, data = build(LAYERED)
    randomize_event_branch(model)
    with torch.no_grad():
        model.bg_layer.texture.add_(0.3)
    path = tmp_path / "m.ckpt"
    save_checkpoint(model, path)
    loaded = load_checkpoint(path)
    assert torch.equal(loaded.gaussians.birth, model.gaussians.birth)
    torch.testing.assert_close(loaded.bg_layer.colors(), model.bg_layer.colors(), atol=0, rtol=0)
    t = int(data.held_out_t_us[0])
    emap = data.event_map(model.tau(t), t)
    for pose in (np.eye(4), _yaw(2.0)):
        a = model.render(model.deform(t, emap), pose, model.meta.intrinsics)
        b = loaded.render(loaded.deform(t, emap), pose, loaded.meta.intrinsics)
        np.testing.assert_array_equal(a, b)


def test_densification_keeps_birth_aligned():
    model, _ = build(LAYERED)
    g = model.gaussians
    optimizer = torch.optim.Adam([{"name": n, "params": [getattr(g, n)]} for n in
                                  ("means", "quats", "log_scales", "opacity_logits", "features")])
    tag = g.means.detach()[:, 0].clone()
    stats = GradientStats(len(g))
    stats.add(torch.linspace(0, 1e-3, len(g)))
    with torch.no_grad():
        g.opacity_logits[:5] = -10.0  # pruned
    before = dict(zip(tag.tolist(), g.birth.tolist(), strict=True))
    densify_and_prune(g, optimizer, stats, grad_threshold=5e-4, extent=float(model.extent),
                      percent_dense=0.01, min_opacity=0.005, max_size=None, max_count=10_000)
    assert g.birth.shape == (len(g),)
    for x, b in zip(g.means.detach()[:, 0].tolist(), g.birth.tolist(), strict=True):
        if x in before:  # kept or cloned rows (split ones moved)
            assert before[x] == b


def test_training_with_layer_and_windows_logs_health(tmp_path):
    model, data = build(LAYERED.replace(iterations=12))
    trainer = Trainer(model, data, progress=False)
    terms = {}
    for _ in range(12):
        terms.update(trainer.train_step())
    assert {"photo", "event", "next", "edisp", "dead"} <= set(terms)
    assert all(math.isfinite(v) for v in terms.values())
    assert 0.0 <= terms["dead"] <= 1.0
    trainer.history = [{"step": 12, "psnr": 20.0, "ssim": 0.5, "frames": 2, "seconds": 1.0, "event": 0.1,
                        "edisp": 1e-3, "dead": 0.0, "gaussians": 900},
                       {"step": 13, "psnr": 20.0, "ssim": 0.5, "frames": 2, "seconds": 1.0}]
    write_history_csv(trainer.history, tmp_path / "h.csv")
    lines = (tmp_path / "h.csv").read_text().splitlines()
    assert lines[0] == "step,psnr,ssim,frames,seconds,event,edisp,dead,gaussians"
    assert lines[1].endswith(",0,900") and lines[2].endswith(",,,,")


def test_real_preset_switches():
    cfg = preset("real")
    assert cfg.bg_layer and cfg.anchor_windows and cfg.event_act == "leaky"
    demo = preset("demo")
    assert not demo.bg_layer and not demo.anchor_windows and demo.event_act == "relu"


def test_control_points_of_a_window_carry_only_its_gaussians():
    model, _ = build(LAYERED)
    cp, birth = model.control, model.gaussians.birth
    assert cp.birth is not None
    counts = torch.bincount(cp.birth, minlength=3)
    assert bool((counts >= TINY.skin_k).all())  # farthest-point sampling covers every window
    assert torch.equal(cp.birth[cp.bind], birth[:, None].expand_as(cp.bind))
    # After densification moved or added Gaussians, rebinding keeps to the windows.
    cp.rebind(model.gaussians.means + 0.01, birth=birth)
    assert torch.equal(cp.birth[cp.bind], birth[:, None].expand_as(cp.bind))
    with pytest.raises(ValueError):
        cp.rebind(model.gaussians.means)


def test_checkpoint_with_a_window_outside_the_anchors_is_refused(tmp_path):
    from edmcgs.errors import CheckpointError

    model, _ = build(LAYERED)
    with torch.no_grad():
        model.gaussians.birth[0] = 7  # three anchors
    path = tmp_path / "bad.ckpt"
    save_checkpoint(model, path)
    with pytest.raises(CheckpointError, match=r"gaussians\.birth"):
        load_checkpoint(path)
