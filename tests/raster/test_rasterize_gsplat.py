"""The gsplat path of ``rasterize`` (the ``cuda`` extra): its camera conventions against our projection on
the CPU (gsplat's own torch implementation of its projection), its choice and refusals, and on a CUDA
device its values and gradients against the float64 reference and the float64 torch path."""

import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError, RenderError
from edmcgs.model.render import rasterize_gsplat, reference
from edmcgs.model.render.projection import LOWPASS, ewa_project
from edmcgs.model.render.rasterize import backend_of, rasterize
from harness.scenes import random_scene

FIELDS = ("means", "quats", "scales", "opacities", "colors")
BG = [0.1, 0.2, 0.3]
HAS_GSPLAT = rasterize_gsplat.available()
needs_gsplat = pytest.mark.skipif(not HAS_GSPLAT, reason="needs gsplat (the cuda extra)")
needs_cuda = pytest.mark.skipif(not (torch.cuda.is_available() and HAS_GSPLAT),
                                reason="needs a CUDA device and gsplat")
LOW_OPACITY = (0.05, 0.34)
"""Below 0.35 no splat's alpha reaches 1/255 beyond 3 sigma or 0.99 anywhere: gsplat's contract and ours
(``rasterize_gsplat``'s docstring) then give the same image."""


def tensors(scene, dtype=torch.float32, device="cpu", grad=False):
    return [torch.tensor(scene[n], dtype=dtype, device=device, requires_grad=grad) for n in FIELDS]


def ref_render(scene, background=None):
    k = scene["intrinsics"]
    return reference.render(*(scene[n] for n in FIELDS), scene["w2c"], k.fx, k.fy, k.cx, k.cy, k.width,
                            k.height, background=background)


@needs_gsplat
def test_camera_conventions_match_our_projection():
    """gsplat's projection (its torch reference) fed our camera gives our pixel positions shifted by its
    half-pixel centres, and our conics and depths."""
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    scene = random_scene(200, 64, 48, seed=3)
    means, quats, scales, _, _ = tensors(scene, torch.float64)
    w2c = torch.tensor(scene["w2c"], dtype=torch.float64)
    k = scene["intrinsics"]
    viewmats, ks = rasterize_gsplat.camera(w2c, k)
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    _, mean2d, depth, conic, _ = _fully_fused_projection(means, covars, viewmats, ks, k.width, k.height,
                                                          eps2d=LOWPASS)
    ours = ewa_project(means, quats, scales, w2c, k, 0.01)
    np.testing.assert_allclose(mean2d[0].numpy() - 0.5, ours.mean2d.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(depth[0].numpy(), ours.depth.numpy(), rtol=1e-12)
    np.testing.assert_allclose(conic[0].numpy(), ours.conic.numpy(), rtol=1e-9, atol=1e-12)


def test_auto_keeps_numba_on_the_cpu_and_gsplat_refuses_it():
    means = torch.zeros(1, 3)
    assert backend_of("auto", means) == "numba"
    assert backend_of("auto", means.half()) == "torch"
    with pytest.raises(InvalidInputError, match="gsplat"):
        backend_of("gsplat", means)


def test_a_missing_gsplat_is_named_with_its_extra(monkeypatch):
    monkeypatch.setattr("edmcgs.model.render.rasterize.gsplat_available", lambda: False)
    monkeypatch.setenv("EDMCGS_RASTERIZER", "gsplat")
    with pytest.raises(InvalidInputError, match=r"EDMCGS_RASTERIZER=gsplat: gsplat is not installed .*cuda"):
        backend_of(None, torch.zeros(1, 3))


@needs_cuda
def test_auto_picks_gsplat_for_float32_on_cuda():
    means = torch.zeros(1, 3, device="cuda")
    assert backend_of("auto", means) == "gsplat"
    assert backend_of("auto", means.double()) == "torch"


@needs_cuda
@pytest.mark.parametrize("sh_degree, channels", [(None, 3), (None, 1), (1, 3), (3, 3), (2, 1)])
def test_cuda_matches_the_reference(sh_degree, channels):
    scene = random_scene(400, 70, 45, seed=11 + (sh_degree or 0), sh_degree=sh_degree, channels=channels,
                         opacity=LOW_OPACITY)
    bg = BG[:channels]
    out = rasterize(*tensors(scene, device="cuda"), scene["w2c"], scene["intrinsics"], background=bg,
                    return_alpha=True, return_depth=True, backend="gsplat")
    image, alpha, depth = ref_render(scene, background=bg)
    assert out.image.shape == (45, 70, channels) and out.image.device.type == "cuda"
    assert alpha.max() > 0.5  # the scene covers the image
    np.testing.assert_allclose(out.image.cpu().numpy(), image, atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.alpha.cpu().numpy(), alpha, atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.depth.cpu().numpy(), depth, atol=1e-3, rtol=0)


@needs_cuda
@pytest.mark.parametrize("sh_degree", [None, 3])
def test_cuda_gradients_match_the_float64_path(sh_degree):
    """Gradients of a weighted image sum against the float64 torch path (which matches the reference to
    ~1e-12, tests/raster/test_rasterize.py): within 1e-3 of each parameter's largest gradient."""
    scene = random_scene(300, 60, 40, seed=5, sh_degree=sh_degree, opacity=LOW_OPACITY)
    weights = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, (40, 60, 3)))
    grads = []
    for device, dtype, backend in (("cuda", torch.float32, "gsplat"), ("cpu", torch.float64, "torch")):
        args = tensors(scene, dtype, device, grad=True)
        out = rasterize(*args, scene["w2c"], scene["intrinsics"], background=BG, backend=backend)
        (out.image * weights.to(device, dtype)).sum().backward()
        grads.append([a.grad.double().cpu().numpy() for a in args])
    for name, got, want in zip(FIELDS, *grads, strict=True):
        assert np.abs(want).max() > 0, name
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-3 * np.abs(want).max(), err_msg=name)


@needs_cuda
def test_cuda_opaque_scenes_stay_close_to_the_reference():
    """With opaque splats the two contracts differ (alpha clamp 0.999, 3.33-sigma boxes): a little."""
    scene = random_scene(400, 70, 45, seed=2, sh_degree=2)
    out = rasterize(*tensors(scene, device="cuda"), scene["w2c"], scene["intrinsics"], background=BG,
                    backend="gsplat")
    diff = np.abs(out.image.cpu().numpy() - ref_render(scene, background=BG)[0])
    assert diff.mean() < 1e-3 and diff.max() < 0.03


@needs_cuda
def test_cuda_empty_scene_is_the_background():
    scene = random_scene(0, 20, 10, seed=0)
    out = rasterize(*tensors(scene, device="cuda"), scene["w2c"], scene["intrinsics"], background=BG,
                    return_alpha=True, backend="gsplat")
    np.testing.assert_array_equal(out.image.cpu().numpy(), np.broadcast_to(np.float32(BG), (10, 20, 3)))
    assert float(out.alpha.abs().max()) == 0


@needs_gsplat
@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU-only case")
def test_without_cuda_the_extension_is_reported_unusable():
    assert "gsplat's CUDA extension" in rasterize_gsplat.extension_error()


def test_an_unusable_extension_is_logged_once_and_refused_when_forced(monkeypatch, caplog):
    monkeypatch.setattr(rasterize_gsplat, "available", lambda: True)
    monkeypatch.setattr(rasterize_gsplat, "extension_error", lambda: "gsplat's CUDA extension: broken")
    rasterize_gsplat._warn_once.cache_clear()
    with caplog.at_level("WARNING"):
        assert not rasterize_gsplat.usable() and not rasterize_gsplat.usable()
    assert [r.getMessage() for r in caplog.records] == [
        "gsplat's CUDA extension: broken: CUDA renders use the torch rasterizer"]
    scene = random_scene(3, 8, 8, seed=0)
    with pytest.raises(RenderError, match=r"broken.*EDMCGS_RASTERIZER=torch"):
        rasterize_gsplat.composite_gsplat(*tensors(scene)[:4], torch.ones(3, 3), torch.eye(4),
                                          scene["intrinsics"], 0.01)
