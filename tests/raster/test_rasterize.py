"""The differentiable rasterizer against the brute-force float64 reference, its gradients, edge cases;
every test on both compositors (torch and numba), chosen through the environment variable."""

import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError, PoseError
from edmcgs.geometry import Intrinsics
from edmcgs.model.render import composite, reference
from edmcgs.model.render.rasterize import rasterize
from harness.scenes import at_camera_depth, random_scene, with_values

FIELDS = ("means", "quats", "scales", "opacities", "colors")
BG = [0.1, 0.2, 0.3]


@pytest.fixture(autouse=True, params=["torch", "numba"])
def backend(request, monkeypatch):
    monkeypatch.setenv("EDMCGS_RASTERIZER", request.param)
    return request.param


def tensors(scene, dtype=torch.float64, grad=False):
    return [torch.tensor(scene[n], dtype=dtype, requires_grad=grad) for n in FIELDS]


def ref_render(scene, background=None, **kw):
    k = scene["intrinsics"]
    return reference.render(*(scene[n] for n in FIELDS), scene["w2c"], k.fx, k.fy, k.cx, k.cy, k.width,
                            k.height, background=background, **kw)


def render(scene, dtype=torch.float64, background=None, grad=False, **kw):
    args = tensors(scene, dtype, grad)
    out = rasterize(*args, scene["w2c"], scene["intrinsics"], background=background, return_depth=True,
                    return_alpha=True, **kw)
    return out, args


def assert_matches(out, ref, atol):
    np.testing.assert_allclose(out.image.detach().numpy(), ref[0], atol=atol, rtol=0)
    np.testing.assert_allclose(out.alpha.detach().numpy(), ref[1], atol=atol, rtol=0)
    np.testing.assert_allclose(out.depth.detach().numpy(), ref[2], atol=atol * 10, rtol=0)


@pytest.mark.parametrize("sh_degree, channels", [(None, 3), (None, 1), (0, 3), (1, 3), (2, 1), (3, 3)])
def test_float64_matches_the_reference_exactly(sh_degree, channels):
    scene = random_scene(150, 53, 37, seed=sh_degree or 7, sh_degree=sh_degree, channels=channels)
    bg = BG[:channels]
    out, _ = render(scene, background=bg)
    ref = ref_render(scene, background=bg)
    assert out.image.shape == (37, 53, channels) and out.image.dtype == torch.float64
    assert ref[1].max() > 0.9  # the scene really covers the image
    assert_matches(out, ref, 1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_float32_matches_the_reference(seed):
    scene = random_scene(400, 70, 45, seed=seed, sh_degree=3)
    out, _ = render(scene, dtype=torch.float32, background=BG)
    assert out.image.dtype == torch.float32
    assert_matches(out, ref_render(scene, background=BG), 1e-4)


def test_opaque_stacks_stop_at_the_transmittance_floor():
    scene = random_scene(300, 40, 30, seed=4, opacity=(0.9, 1.0), px_sigma=(4.0, 10.0))
    out, _ = render(scene, background=BG)
    ref = ref_render(scene, background=BG)
    assert (ref[1] > 1 - 2e-4).mean() > 0.5  # most pixels reach the floor and stop
    assert_matches(out, ref, 1e-10)


def test_image_does_not_depend_on_block_size_or_round_budget(monkeypatch):
    scene = random_scene(300, 50, 40, seed=5, sh_degree=1)
    base, _ = render(scene, background=BG, backend="torch")
    for block, budget in [(16, 1 << 21), (4, 1 << 21), (8, 4096)]:
        monkeypatch.setattr(composite, "BLOCK", block)
        monkeypatch.setattr(composite, "ROUND_ELEMENTS", budget)
        out, _ = render(scene, background=BG, backend="torch")
        for a, b in zip((out.image, out.alpha, out.depth), (base.image, base.alpha, base.depth), strict=True):
            np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-12, rtol=0)


def test_single_gaussian_by_hand():
    """One round Gaussian of opacity o centred on a pixel: that pixel is o c + (1 - o) bg."""
    k = Intrinsics(100.0, 100.0, 4.0, 3.0, 9, 7)
    out = rasterize(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
                    torch.full((1, 3), 0.02), torch.tensor([0.6]), torch.tensor([[1.0, 0.5, 0.0]]),
                    np.eye(4), k, background=BG, return_alpha=True, return_depth=True)
    np.testing.assert_allclose(out.image[3, 4].numpy(), 0.6 * np.array([1, 0.5, 0]) + 0.4 * np.array(BG),
                               rtol=1e-6)
    assert out.alpha[3, 4] == pytest.approx(0.6)
    assert out.depth[3, 4] == pytest.approx(2.0)
    # sigma^2 = (100 * 0.02 / 2)^2 + 0.3 px^2 along x, one pixel right of the centre:
    var = 1.0 + 0.3
    assert out.alpha[3, 5] == pytest.approx(0.6 * np.exp(-0.5 / var), rel=1e-6)


# ------------------------------------------------------------------------------------ gradients

def _gradcheck(scene, fast_mode):
    args = tensors(scene, grad=True)

    def f(*a):
        out = rasterize(*a, scene["w2c"], scene["intrinsics"], background=BG, return_depth=True,
                        return_alpha=True)
        return out.image, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast_mode)


def test_gradcheck_plain_colors():
    _gradcheck(random_scene(4, 9, 6, seed=11, opacity=(0.3, 0.8), px_sigma=(1.0, 3.0)), fast_mode=False)
    _gradcheck(random_scene(12, 26, 20, seed=10, opacity=(0.3, 0.8)), fast_mode=True)


@pytest.mark.parametrize("degree", [1, 3])
def test_gradcheck_spherical_harmonics(degree):
    scene = random_scene(12, 26, 20, seed=12 + degree, sh_degree=degree, opacity=(0.3, 0.8))
    _gradcheck(scene, fast_mode=True)


def test_gradients_reach_every_parameter():
    scene = random_scene(60, 40, 30, seed=13, sh_degree=2)
    out, args = render(scene, dtype=torch.float32, background=BG, grad=True)
    (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for name, a in zip(FIELDS, args, strict=True):
        assert torch.isfinite(a.grad).all(), name
        assert (a.grad.abs().sum(-1) > 0 if a.grad.ndim > 1 else a.grad.abs() > 0).float().mean() > 0.5, name


# ----------------------------------------------------------------------------------- edge cases

def test_behind_the_camera_and_in_front_of_the_near_plane_are_culled_without_nan():
    scene = random_scene(40, 40, 30, seed=14)
    near = 0.5
    # behind, at the camera, just in front of the near plane: culled; just beyond it: kept
    scene = at_camera_depth(scene, slice(0, 4), [-3.0, -1e-9, 0.0, near * (1 - 1e-3)])
    scene = at_camera_depth(scene, slice(4, 6), [near * (1 + 1e-3), 0.51])
    out, args = render(scene, background=BG, grad=True, near=near)
    assert_matches(out, ref_render(scene, background=BG, near=near), 1e-9)
    (out.image.sum() + out.depth.sum()).backward()
    for a in args:
        assert torch.isfinite(a.grad).all()
        assert (a.grad[:4] == 0).all()  # culled: exactly no gradient


def test_on_the_near_plane_is_finite_either_way():
    """Exactly on z = near, one ulp of the depth decides culling: only finiteness and range are defined."""
    near = 0.5
    scene = at_camera_depth(random_scene(40, 40, 30, seed=14), slice(0, 3), [near] * 3)
    out, args = render(scene, background=BG, grad=True, near=near)
    for image in (out.image, out.alpha, out.depth):
        assert torch.isfinite(image).all()
    assert out.image.min() >= 0 and out.image.max() <= 1 and out.alpha.max() <= 1 and out.depth.min() >= 0
    (out.image.sum() + out.depth.sum()).backward()
    assert all(torch.isfinite(a.grad).all() for a in args)


@pytest.mark.parametrize("scale", [1e-8, 1e-3, 1.0, 1e3])
def test_extreme_scales_stay_finite_and_match(scale):
    scene = random_scene(30, 40, 30, seed=15)
    scene = with_values(scene, scales=(slice(0, 10), scale))
    scene = with_values(scene, scales=((slice(10, 15), 0), scale))  # one extreme axis: needles / pancakes
    out, args = render(scene, background=BG, grad=True)
    assert_matches(out, ref_render(scene, background=BG), 1e-8)
    (out.image.sum() + out.depth.sum()).backward()
    assert all(torch.isfinite(a.grad).all() for a in args)


def test_flat_covariances_zero_scale_axes():
    scene = random_scene(30, 40, 30, seed=16, px_sigma=(2.0, 5.0))
    scene = with_values(scene, scales=((slice(0, 10), 2), 0.0))                 # flat discs
    scene = with_values(scene, scales=((slice(10, 20), slice(1, 3)), 0.0))     # lines
    scene = with_values(scene, scales=(slice(20, 25), 0.0))                     # points: just the low-pass
    out, args = render(scene, background=BG, grad=True)
    assert_matches(out, ref_render(scene, background=BG), 1e-9)
    out.image.sum().backward()
    assert all(torch.isfinite(a.grad).all() for a in args)


@pytest.mark.parametrize("opacity", [1.0, 1 - 1e-7])
def test_opacity_near_one_is_clamped(opacity):
    scene = with_values(random_scene(20, 30, 20, seed=17), opacities=(slice(None), opacity))
    out, _ = render(scene, background=BG)
    assert_matches(out, ref_render(scene, background=BG), 1e-9)
    assert out.alpha.max() <= 1 - 1e-4 + 1e-12


@pytest.mark.parametrize("n", [0, 5])
def test_empty_or_fully_culled_scene_is_background(n):
    scene = random_scene(max(n, 1), 20, 10, seed=18)
    scene = {k: (v[:n] if k in FIELDS else v) for k, v in scene.items()}
    if n:
        scene = at_camera_depth(scene, slice(None), [-1.0] * n)
    out, args = render(scene, background=BG, grad=True)
    assert out.image.shape == (10, 20, 3)
    np.testing.assert_array_equal(out.image.detach().numpy(), np.broadcast_to(BG, (10, 20, 3)))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    out.image.sum().backward()  # still a graph: training on an empty view does not crash
    assert all((a.grad == 0).all() for a in args)


@pytest.mark.parametrize("width, height", [(1, 1), (17, 1), (1, 23), (16, 16), (33, 2)])
def test_tiny_and_thin_images(width, height):
    scene = random_scene(50, width, height, seed=width * 31 + height, px_sigma=(0.5, 3.0), margin=1.0)
    out, args = render(scene, background=BG, grad=True)
    assert out.image.shape == (height, width, 3)
    assert_matches(out, ref_render(scene, background=BG), 1e-10)
    out.image.sum().backward()
    assert all(torch.isfinite(a.grad).all() for a in args)


def test_no_nan_from_wild_but_finite_inputs():
    rng = np.random.default_rng(19)
    n = 300
    k = Intrinsics(50.0, 50.0, 15.5, 10.5, 32, 22)
    means = rng.normal(size=(n, 3)) * np.exp(rng.uniform(-20, 8, (n, 1)))
    quats = rng.normal(size=(n, 4)) * np.exp(rng.uniform(-30, 30, (n, 1)))
    scales = np.exp(rng.uniform(-25, 7, (n, 3)))
    opac = rng.uniform(0, 1, n)
    opac[:20] = [0.0, 1.0] * 10
    args = [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in (means, quats, scales, opac,
                                                                               rng.normal(size=(n, 9, 3)))]
    out = rasterize(*args, np.eye(4), k, return_alpha=True, return_depth=True, near=1e-6)
    for t in (out.image, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert all(torch.isfinite(a.grad).all() for a in args)


# -------------------------------------------------------------------------------------- bad input

def _good():
    s = random_scene(5, 10, 8, seed=20)
    return dict(zip(FIELDS, tensors(s, torch.float32), strict=True)), s["w2c"], s["intrinsics"]


@pytest.mark.parametrize("name", FIELDS)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_input_names_the_argument(name, bad):
    args, w2c, k = _good()
    args[name] = args[name].clone()
    args[name].view(-1)[1] = bad
    with pytest.raises(InvalidInputError, match=f"{name} contains NaN or Inf"):
        rasterize(*args.values(), w2c, k)


@pytest.mark.parametrize("name, value, message", [
    ("means", torch.zeros(5, 2), "means must have shape"),
    ("quats", torch.zeros(4, 4), r"quats must have shape \[5, 4\]"),
    ("scales", -torch.ones(5, 3), "scales must be >= 0"),
    ("opacities", torch.full((5,), 1.5), r"opacities must lie in \[0, 1\]"),
    ("opacities", torch.zeros(5, 1), "opacities must have shape"),
    ("quats", torch.zeros(5, 4), "zero quaternion"),
    ("colors", torch.zeros(5, 2), "colors must be"),
    ("colors", torch.zeros(5, 5, 3), "colors must be"),
    ("colors", torch.zeros(5, 3, dtype=torch.float64), "colors must match means' dtype"),
    ("means", np.zeros((5, 3), np.float32), "means must be a torch.Tensor"),
    ("quats", np.zeros((5, 4), np.float32), "quats must be a torch.Tensor"),
])
def test_bad_arguments_are_named(name, value, message):
    args, w2c, k = _good()
    args[name] = value
    with pytest.raises(InvalidInputError, match=message):
        rasterize(*args.values(), w2c, k)


def test_bad_camera_and_options_are_named():
    args, w2c, k = _good()
    bad = np.array(w2c)
    bad[0, 3] = np.nan
    with pytest.raises(PoseError, match="w2c"):
        rasterize(*args.values(), bad, k)
    with pytest.raises(InvalidInputError, match="near"):
        rasterize(*args.values(), w2c, k, near=0.0)
    with pytest.raises(InvalidInputError, match="background"):
        rasterize(*args.values(), w2c, k, background=[0.0, 1.0])
    with pytest.raises(InvalidInputError, match="background"):
        rasterize(*args.values(), w2c, k, background=[np.nan] * 3)
    with pytest.raises(InvalidInputError, match="intrinsics"):
        rasterize(*args.values(), w2c, (10, 10, 5, 5, 10, 8))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    """The torch path on CUDA (gsplat's, chosen by auto where installed: test_rasterize_gsplat.py)."""
    scene = random_scene(300, 60, 40, seed=21, sh_degree=2)
    cpu, _ = render(scene, dtype=torch.float32, background=BG)
    args = [t.cuda().requires_grad_() for t in tensors(scene, torch.float32)]
    out = rasterize(*args, scene["w2c"], scene["intrinsics"], background=BG, return_alpha=True,
                    return_depth=True, backend="torch")
    assert out.image.device.type == "cuda"
    np.testing.assert_allclose(out.image.detach().cpu().numpy(), cpu.image.numpy(), atol=1e-4)
    out.image.sum().backward()
    assert all(torch.isfinite(a.grad).all() for a in args)
