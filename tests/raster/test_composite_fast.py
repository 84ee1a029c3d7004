"""The numba compositor (forward + analytic backward) against the torch compositor it stands in for:
same images, same gradients (down to the screen-space means densification reads), gradcheck in
float64, degenerate scenes, and the switch between the two."""

import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.model.render import rasterize as rasterize_module
from edmcgs.model.render.composite import composite, make_plan
from edmcgs.model.render.composite_fast import composite_fast
from edmcgs.model.render.projection import ewa_project, screen_rect
from edmcgs.model.render.rasterize import rasterize
from harness.scenes import random_scene, with_values

FIELDS = ("means", "quats", "scales", "opacities", "colors")
BG = [0.1, 0.2, 0.3]
# float32: both paths round differently (simd exp against torch.exp, block-local against
# tile-local coordinates); differences are a few float32 ulps of the values they sum.
TOL = {torch.float64: dict(image=1e-12, depth=1e-11, grad=1e-9), torch.float32: dict(image=1e-5, depth=1e-4,
                                                                                    grad=2e-4)}
SCENES = {
    "sh3": dict(n=400, width=70, height=45, seed=1, sh_degree=3),
    "grey": dict(n=300, width=53, height=37, seed=2, channels=1),
    "opaque-stack": dict(n=300, width=40, height=30, seed=4, opacity=(0.9, 1.0), px_sigma=(4.0, 10.0)),
    "wide": dict(n=200, width=66, height=50, seed=5, px_sigma=(3.0, 20.0), opacity=(0.05, 0.6)),
}


def _scene(name):
    kw = dict(SCENES[name])
    return random_scene(kw.pop("n"), kw.pop("width"), kw.pop("height"), **kw)


def _render_and_grad(scene, backend, dtype):
    """Image, alpha and depth of one render and the gradients of a fixed random loss over all three."""
    args = [torch.tensor(scene[n], dtype=dtype, requires_grad=True) for n in FIELDS]
    bg = BG[:scene["colors"].shape[-1]]
    out = rasterize(*args, scene["w2c"], scene["intrinsics"], background=bg, return_alpha=True,
                    return_depth=True, backend=backend)
    gen = torch.Generator().manual_seed(0)
    weights = [torch.rand(t.shape, generator=gen, dtype=dtype) for t in (out.image, out.alpha, out.depth)]
    loss = (out.image * weights[0]).sum() + (out.alpha * weights[1]).sum()
    (loss + 0.1 * (out.depth * weights[2]).sum()).backward()
    return out, [a.grad for a in args]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", sorted(SCENES))
def test_forward_and_gradients_match_the_torch_path(name, dtype):
    scene = _scene(name)
    ref, ref_grads = _render_and_grad(scene, "torch", dtype)
    out, grads = _render_and_grad(scene, "numba", dtype)
    tol = TOL[dtype]
    assert out.image.dtype == dtype and out.image.shape == ref.image.shape
    for key in ("image", "alpha", "depth"):
        np.testing.assert_allclose(getattr(out, key).detach().numpy(), getattr(ref, key).detach().numpy(),
                                   atol=tol["depth" if key == "depth" else "image"], rtol=0, err_msg=key)
    for field, g, r in zip(FIELDS, grads, ref_grads, strict=True):
        scale = float(r.abs().max())
        assert scale > 0, field
        err = float((g - r).abs().max()) / scale
        assert err <= tol["grad"], f"{field}: max |numba - torch| / max |torch| = {err:.2e}"


def _splats(scene, dtype):
    """What rasterize hands a compositor: attrs [M, 6] (leaf, grad), feat [M, 4] (leaf), rect, depth."""
    t = {n: torch.tensor(scene[n], dtype=dtype) for n in FIELDS}
    k = scene["intrinsics"]
    w2c = torch.tensor(scene["w2c"], dtype=dtype)
    sp = ewa_project(t["means"], t["quats"], t["scales"], w2c, k, 0.01)
    rect = screen_rect(sp, t["opacities"], k.width, k.height, 0.01)
    keep = ((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])).nonzero().squeeze(1)
    attrs = torch.cat([sp.mean2d, sp.conic, t["opacities"][:, None]], -1)[keep].detach().requires_grad_()
    feat = torch.cat([t["colors"], sp.depth[:, None]], -1)[keep].detach().requires_grad_()
    return attrs, feat, rect[keep], sp.depth[keep], k.width, k.height


@pytest.mark.parametrize("name", ["wide", "opaque-stack"])
def test_screen_space_gradients_match_the_torch_compositor(name):
    """The gradients of the 2D means (what densification reads), conics, opacities and features."""
    scene = _scene(name)
    attrs, feat, rect, depth, w, h = _splats(scene, torch.float32)
    gen = torch.Generator().manual_seed(1)
    g_acc = torch.rand(h, w, feat.shape[1], generator=gen)
    g_t = torch.rand(h, w, generator=gen) - 0.5
    grads = []
    for numba_path in (False, True):
        attrs.grad = feat.grad = None
        if numba_path:
            acc, trans = composite_fast(attrs, feat, rect, depth, w, h)
        else:
            acc, trans = composite(attrs, feat, make_plan(rect, depth, w, h))
        ((acc * g_acc).sum() + (trans * g_t).sum()).backward()
        grads.append((attrs.grad.clone(), feat.grad.clone()))
    (ta, tf), (na, nf) = grads
    names = ["mean x", "mean y", "conic A", "conic B", "conic C", "opacity"]
    for i, col in enumerate(names):
        err = float((na[:, i] - ta[:, i]).abs().max() / ta[:, i].abs().max())
        assert err < 2e-4, f"{col}: {err:.2e}"
    assert float((nf - tf).abs().max() / tf.abs().max()) < 2e-4


@pytest.mark.parametrize("size, seed, fast_mode", [((4, 9, 6), 0, False), ((10, 21, 17), 0, True),
                                                   ((10, 21, 17), 1, True)])
def test_gradcheck_float64(size, seed, fast_mode):
    """The whole Jacobian on a tiny scene (one backward per output pixel); on larger ones its products
    with random vectors (gradcheck's fast mode), which any wrong entry changes too."""
    scene = random_scene(*size, seed=30 + seed, opacity=(0.3, 0.8), px_sigma=(1.0, 4.0))
    attrs, feat, rect, depth, w, h = _splats(scene, torch.float64)
    assert attrs.shape[0] >= min(5, size[0])

    def f(a, c):
        return composite_fast(a, c, rect, depth, w, h)

    assert torch.autograd.gradcheck(f, (attrs, feat), eps=1e-6, atol=1e-7, rtol=1e-5, fast_mode=fast_mode)


def test_no_gaussians_in_view():
    attrs = torch.zeros(0, 6, requires_grad=True)
    feat = torch.zeros(0, 3, requires_grad=True)
    acc, trans = composite_fast(attrs, feat, torch.zeros(0, 4, dtype=torch.long), torch.zeros(0), 19, 7)
    assert acc.shape == (7, 19, 3) and trans.shape == (7, 19)
    assert (acc == 0).all() and (trans == 1).all()
    (acc.sum() + trans.sum()).backward()
    assert attrs.grad.shape == (0, 6) and feat.grad.shape == (0, 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["tiny", "huge", "needles", "opacity-one", "opacity-floor"])
def test_degenerate_gaussians_are_finite_and_match(case, dtype):
    scene = random_scene(60, 40, 30, seed=40, sh_degree=1)
    if case == "tiny":
        scene = with_values(scene, scales=(slice(0, 30), 1e-8))
    elif case == "huge":
        scene = with_values(scene, scales=(slice(0, 5), 30.0))
    elif case == "needles":
        scene = with_values(scene, scales=((slice(0, 30), slice(0, 2)), 1e-9))
    elif case == "opacity-one":
        scene = with_values(scene, opacities=(slice(0, 40), [1.0, 1 - 1e-7, 0.99, 0.995] * 10))
    else:  # at, just above and just below the skip threshold, and 0
        floor = 1 / 255
        scene = with_values(scene, opacities=(slice(0, 40), [floor, floor + 1e-7, floor - 1e-7, 0.0] * 10))
    ref, ref_grads = _render_and_grad(scene, "torch", dtype)
    out, grads = _render_and_grad(scene, "numba", dtype)
    for t in (out.image, out.alpha, out.depth, *grads):
        assert torch.isfinite(t).all()
    np.testing.assert_allclose(out.image.detach().numpy(), ref.image.detach().numpy(),
                               atol=TOL[dtype]["image"], rtol=0)
    for field, g, r in zip(FIELDS, grads, ref_grads, strict=True):
        scale = max(float(r.abs().max()), 1e-30)
        assert float((g - r).abs().max()) / scale <= TOL[dtype]["grad"] * 10, field


def test_environment_variable_forces_the_torch_path(monkeypatch):
    scene = random_scene(20, 20, 16, seed=50)
    args = [torch.tensor(scene[n], dtype=torch.float32) for n in FIELDS]

    def refuse(*a, **k):
        raise AssertionError("the numba compositor ran")

    monkeypatch.setattr(rasterize_module, "composite_fast", refuse)
    monkeypatch.setenv("EDMCGS_RASTERIZER", "torch")
    rasterize(*args, scene["w2c"], scene["intrinsics"])
    monkeypatch.delenv("EDMCGS_RASTERIZER")
    with pytest.raises(AssertionError, match="numba compositor ran"):  # auto on the CPU: numba
        rasterize(*args, scene["w2c"], scene["intrinsics"])
    monkeypatch.setenv("EDMCGS_RASTERIZER", "cuda")
    with pytest.raises(InvalidInputError, match="EDMCGS_RASTERIZER must be one of auto, torch, numba"):
        rasterize(*args, scene["w2c"], scene["intrinsics"])
    with pytest.raises(InvalidInputError, match="backend must be one of"):
        rasterize(*args, scene["w2c"], scene["intrinsics"], backend="gpu")
    half = [a.to(torch.bfloat16) for a in args]  # auto: a dtype the kernels do not take goes to torch
    monkeypatch.delenv("EDMCGS_RASTERIZER")
    assert rasterize(*half, scene["w2c"], scene["intrinsics"]).image.dtype == torch.bfloat16
    with pytest.raises(InvalidInputError, match="numba renders float32 or float64 tensors on the CPU"):
        rasterize(*half, scene["w2c"], scene["intrinsics"], backend="numba")


def test_torch_thread_count_is_left_alone():
    scene = random_scene(50, 30, 20, seed=51)
    args = [torch.tensor(scene[n], dtype=torch.float32, requires_grad=True) for n in FIELDS]
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        rasterize(*args, scene["w2c"], scene["intrinsics"], backend="numba").image.sum().backward()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
