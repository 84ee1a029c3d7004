"""The numba projection and SH colour (forward + analytic backward) against the torch versions they
stand in for (``projection.ewa_project``, ``sh.sh_to_color``), and float64 gradcheck."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from edmcgs.model.render.project_fast import project_fast, sh_color_fast
from edmcgs.model.render.projection import ewa_project
from edmcgs.model.render.sh import sh_to_color
from harness.scenes import at_camera_depth, random_scene, with_values

NEAR = 0.01


def _leaves(scene, names, dtype=torch.float64):
    return [torch.tensor(scene[n], dtype=dtype, requires_grad=True) for n in names]


def _weights(shapes, dtype):
    gen = torch.Generator().manual_seed(3)
    return [torch.rand(s, generator=gen, dtype=dtype) - 0.5 for s in shapes]


def _projection_grads(scene, fast, dtype):
    means, quats, scales = _leaves(scene, ("means", "quats", "scales"), dtype)
    k = scene["intrinsics"]
    if fast:
        mean2d, cov2d, conic, depth = project_fast(means, quats, scales, scene["w2c"], k, NEAR)
    else:
        sp = ewa_project(means, quats, scales, torch.tensor(scene["w2c"], dtype=dtype), k, NEAR)
        mean2d, cov2d, conic, depth = sp.mean2d, sp.cov2d, sp.conic, sp.depth
    wm, wc, wd = _weights([mean2d.shape, conic.shape, depth.shape], dtype)
    ((mean2d * wm).sum() + (conic * wc).sum() + (depth * wd).sum()).backward()
    return [t.detach() for t in (mean2d, cov2d, conic, depth)], [means.grad, quats.grad, scales.grad]


def _scenes():
    base = random_scene(80, 60, 40, seed=60, margin=0.5)
    flat = with_values(base, scales=((slice(0, 20), 2), 0.0))               # discs and needles
    flat = with_values(flat, scales=((slice(20, 30), slice(0, 2)), 1e-9))
    wide = at_camera_depth(base, slice(0, 10), [0.05] * 10)                  # off-frustum x/z, y/z clamps
    return {"random": base, "flat": flat, "near-and-wide": wide}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", ["random", "flat", "near-and-wide"])
def test_projection_matches_the_torch_projection(name, dtype):
    scene = _scenes()[name]
    ref_out, ref_grads = _projection_grads(scene, False, dtype)
    out, grads = _projection_grads(scene, True, dtype)
    rtol = 1e-10 if dtype == torch.float64 else 2e-4
    for label, a, b in zip(("mean2d", "cov2d", "conic", "depth"), out, ref_out, strict=True):
        assert a.dtype == dtype
        err = float(((a - b).abs() / (b.abs() + 1e-3 * b.abs().max())).max())
        assert err < rtol, f"{label}: {err:.2e}"
    for label, a, b in zip(("means", "quats", "scales"), grads, ref_grads, strict=True):
        assert torch.isfinite(a).all()
        err = float((a - b).abs().max() / b.abs().max())
        assert err < rtol, f"d {label}: {err:.2e}"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("channels", [1, 3])
def test_sh_colour_matches_the_torch_colour(degree, channels):
    scene = random_scene(60, 30, 20, seed=61 + degree, sh_degree=degree, channels=channels)
    w2c = scene["w2c"]
    centre = torch.tensor(-(w2c[:3, :3].T @ w2c[:3, 3]))
    results = []
    for fast in (False, True):
        coeffs, means = _leaves(scene, ("colors", "means"))
        if fast:
            color = sh_color_fast(coeffs, means, w2c)
        else:
            color = sh_to_color(coeffs, F.normalize(means - centre, dim=-1, eps=1e-12))
        (color * _weights([color.shape], torch.float64)[0]).sum().backward()
        results.append((color.detach(), coeffs.grad, means.grad))
    assert (results[0][0] == 0).any() or degree == 0  # some colours clamped at 0: that edge is covered
    for a, b in zip(results[1], results[0], strict=True):
        if a is None or b is None:  # degree 0: neither colour reaches the means
            assert degree == 0 and a is None and b is None
            continue
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-10, atol=1e-12)


def test_gradcheck_float64():
    scene = random_scene(6, 30, 20, seed=62, sh_degree=2)
    means, quats, scales, coeffs = _leaves(scene, ("means", "quats", "scales", "colors"))
    k, w2c = scene["intrinsics"], scene["w2c"]

    def f(m, q, s, c):
        mean2d, _, conic, depth = project_fast(m, q, s, w2c, k, NEAR)
        return mean2d, conic, depth, sh_color_fast(c, m, w2c)

    assert torch.autograd.gradcheck(f, (means, quats, scales, coeffs), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gaussians_without_incoming_gradient_get_exactly_zero():
    """Culled Gaussians (behind the camera, degenerate) get no gradient downstream: zero, never NaN."""
    scene = at_camera_depth(random_scene(10, 30, 20, seed=63), slice(0, 5), [-1.0, 0.0, 1e-12, -1e-9, 0.0])
    means, quats, scales = _leaves(scene, ("means", "quats", "scales"))
    mean2d, _, conic, depth = project_fast(means, quats, scales, scene["w2c"], scene["intrinsics"], NEAR)
    keep = torch.arange(5, 10)
    (mean2d[keep].sum() + conic[keep].sum() + depth[keep].sum()).backward()
    for g in (means.grad, quats.grad, scales.grad):
        assert torch.isfinite(g).all()
        assert (g[:5] == 0).all() and (g[5:].abs().sum(-1) > 0).all()
