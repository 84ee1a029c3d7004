"""Saturated frames: pure black and pure white anchors (log of 0 in the event loss).

The simulator's side (black <-> white frames fire finite events, log(0 + eps) finite) is covered by
tests/synth/test_esim.py::test_saturated_black_and_white_frames_stay_finite.
"""

import math

import numpy as np
import torch

from edmcgs.geometry import Trajectory
from edmcgs.model.data import TrainingData
from edmcgs.model.dynamic import EdMCGS
from edmcgs.model.train.losses import event_loss, log_luminance, photometric_loss
from edmcgs.model.train.trainer import Trainer
from tests.support import tiny_scene
from tests.support.models import TINY

C, EPS = 0.2, 1e-3


def test_event_loss_on_black_and_white_renders_is_finite_with_finite_gradients():
    black = torch.zeros(16, 17, 3, requires_grad=True)
    white = torch.ones(16, 17, 3, requires_grad=True)
    events = torch.full((16, 17), 35.0)  # log(1 + eps) - log(eps) = 6.9 = 34.5 C: black -> white
    loss = event_loss(black, white, events, C, EPS)
    assert math.isfinite(loss.item()) and loss.item() < 0.5 * C  # the events explain the jump
    loss.backward()
    assert torch.isfinite(black.grad).all() and torch.isfinite(white.grad).all()
    # a render that undershoots 0 (not from our rasterizer, but from any caller) is clamped, not NaN
    assert torch.isfinite(log_luminance(torch.full((2, 2, 1), -1.0), EPS)).all()
    photo = photometric_loss(black, torch.ones(16, 17, 3), 0.2)
    photo.backward()
    assert math.isfinite(photo.item()) and torch.isfinite(black.grad).all()


def test_training_on_black_and_white_anchors_stays_finite():
    """Anchors black, white, black 100 ms apart; the event source says so (a full-frame flash)."""
    t = tiny_scene.T0 + np.array([0, 100_000, 200_000], np.int64)
    levels = [0.0, 1.0, 0.0]
    images = np.stack([np.full((tiny_scene.H, tiny_scene.W, 3), round(255 * v), np.uint8) for v in levels])

    def luminance_at(t_us: int) -> float:
        return float(np.interp(t_us, t, levels))

    def event_map(t0: int, t1: int) -> np.ndarray:
        step = (math.log(luminance_at(t1) + EPS) - math.log(luminance_at(t0) + EPS)) / C
        return np.full((tiny_scene.H, tiny_scene.W), float(np.trunc(step)), np.float32)

    poses = np.repeat(np.eye(4)[None], 3, 0)
    data = TrainingData(anchors_t_us=t, anchor_images=images, anchor_poses=poses,
                        intrinsics=tiny_scene.INTRINSICS, trajectory=Trajectory(t, poses),
                        t_end_us=int(t[-1]), event_map=event_map, held_out_t_us=t[:2] + 50_000,
                        held_out_images=images[:2])
    cfg = TINY.replace(iterations=12, event_warmup=(0.0, 0.1), densify_from=0.3, densify_every=4)
    model = EdMCGS.from_arrays(anchors_t_us=t, anchor_images=images, intrinsics=data.intrinsics,
                               anchor_poses=poses, t_end_us=data.t_end_us, trajectory=data.trajectory,
                               config=cfg)
    trainer = Trainer(model, data, progress=False)
    for _ in range(cfg.iterations):
        out = trainer.train_step()
        assert all(math.isfinite(v) for v in out.values()), out
    for name, p in model.named_parameters():
        assert torch.isfinite(p).all(), name
    model.eval()
    scores = trainer.evaluate()
    assert math.isfinite(scores["psnr"]) and math.isfinite(scores["ssim"])
    for t_us in (int(t[0]), int(t[0]) + 50_000, int(t[1])):
        state = model.deform(t_us, event_map(int(t[0]), t_us) if t_us > t[0] else None)
        img = model.render(state, np.eye(4), model.meta.intrinsics)
        assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0
