"""``projection.may_draw``, the view cull of a training step: it never drops a Gaussian the rasterizer would
draw (``screen_rect`` non-empty), even after the Gaussian moved by up to ``reach`` and grew by ``growth``,
and it drops most of what lies far off the screen."""

import numpy as np
import pytest
import torch

from edmcgs.geometry import Intrinsics
from edmcgs.model.render.projection import NEAR, ewa_project, may_draw, screen_rect
from harness.scenes import random_scene


def _drawn(means, quats, scales, opacities, w2c, k) -> torch.Tensor:
    splats = ewa_project(means, quats, scales, w2c, k, NEAR)
    rect = screen_rect(splats, opacities, k.width, k.height, NEAR)
    return (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])


def _hostile(seed: int):
    """Gaussians far past the image edges, sub-pixel to larger than the view, from behind the camera to
    across its near plane, opaque (the alpha ellipse at its widest), seen by an off-centre camera."""
    s = random_scene(4000, 96, 64, seed=seed, px_sigma=(0.05, 300.0), depth=(0.002, 30.0), opacity=(1.0, 1.0),
                     margin=3.0)
    rng = np.random.default_rng(seed)
    k = Intrinsics(70.0, 90.0, 20.0, 50.0, 96, 64)
    cam = s["means"] @ s["w2c"][:3, :3].T + s["w2c"][:3, 3]
    cam[:500, 2] *= -1  # behind the camera
    cam[500:700, 2] = rng.uniform(-0.05, 0.05, 200)  # across the near plane
    c2w = np.linalg.inv(s["w2c"])
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    f32 = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return (f32(means), f32(s["quats"]), f32(s["scales"]), f32(s["opacities"]), f32(s["w2c"]), k)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_cull_keeps_every_gaussian_a_render_draws_and_drops_most_far_off_screen(seed):
    means, quats, scales, opacities, w2c, k = _hostile(seed)
    drawn = _drawn(means, quats, scales, opacities, w2c, k)
    kept = may_draw(means, scales.amax(-1), w2c, k, NEAR)
    assert bool(drawn.any()) and not bool((drawn & ~kept).any())
    assert float(kept.float().mean()) < 0.6  # it culls: most of these lie far off the view
    assert float(kept.float().mean()) > float(drawn.float().mean())


@pytest.mark.parametrize("seed", [3, 4])
def test_the_cull_keeps_what_a_render_draws_after_the_gaussians_moved_within_reach(seed):
    means, quats, scales, opacities, w2c, k = _hostile(seed)
    reach, growth = 0.05, 1.3
    kept = may_draw(means, scales.amax(-1), w2c, k, NEAR, reach=reach, growth=growth)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(5):
        step = torch.randn(means.shape, generator=gen)
        step = step / step.norm(dim=-1, keepdim=True) * reach * torch.rand(len(means), 1, generator=gen)
        grown = scales * (1 + (growth - 1) * torch.rand(len(means), 1, generator=gen))
        drawn = _drawn(means + step, quats, grown, opacities, w2c, k)
        assert not bool((drawn & ~kept).any())
    assert float(kept.float().mean()) < 0.8
