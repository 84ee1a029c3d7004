"""float32 against float64 on the same scene: the synthetic benchmark's own Gaussians (dense, many
layers per pixel), rendered by the float32 paths (torch and numba) and by the float64 torch path,
which equals the brute-force reference to 1e-10 (tests/raster/test_rasterize.py::
test_float64_matches_the_reference_exactly). Random scenes: test_float32_matches_the_reference there.

The bound: float32 rounding alone moves a pixel by ~1e-7 on average and by at most ~2e-6 (measured
against the reference with t_min = 0). The larger differences come from the early stop: a pixel stops
before the splat that would take its transmittance T below t_min = 1e-4, so where float32 and float64
disagree on that splat, one side drops alpha * T * |colour - background| with T * (1 - alpha) < t_min,
up to 99 t_min in theory (alpha is clamped at 0.99); measured 4.1e-4 on mutant against black, 1.4e-4
against its grey background. Stated here as max |float32 - float64| <= 1e-3 (the fast path's contract
against the torch one) and, over the pixels the object covers, a mean <= 1e-6.
"""

import numpy as np
import pytest
import torch

from edmcgs.geometry import world_to_camera
from edmcgs.model.render.rasterize import rasterize
from edmcgs.model.render.rasterize_fast import rasterize_fast
from edmcgs.synth.scene import make_scene

MAX_ABS, MEAN_ABS = 1e-3, 1e-6


@pytest.mark.parametrize("name", ["jumpingjack", "mutant"])
def test_float32_renders_match_float64_on_a_benchmark_scene(name):
    scene = make_scene(name, "small")
    g = scene.gaussians_at(1.0)
    w2c, k = world_to_camera(scene.camera_at(1.0)), scene.intrinsics
    bg = np.asarray(scene.background)
    arrays = [np.asarray(a) for a in (g.means, g.quats, g.scales, g.opacities, g.colors)]
    f64 = rasterize(*(torch.tensor(a, dtype=torch.float64) for a in arrays), w2c, k, background=bg,
                    return_alpha=True)
    covered = f64.alpha.numpy() > 0.01
    assert covered.mean() > 0.08  # the object fills a good part of the frame
    f64 = f64.image.numpy()
    f32 = rasterize(*(torch.tensor(a, dtype=torch.float32) for a in arrays), w2c, k, background=bg)
    f32 = f32.image.numpy()
    fast = rasterize_fast(*arrays, w2c.astype(np.float32), k, background=bg.astype(np.float32)).image
    for img in (f32, fast):
        diff = np.abs(img.astype(np.float64) - f64)
        assert diff.max() <= MAX_ABS and diff[covered].mean() <= MEAN_ABS, (diff.max(), diff[covered].mean())
