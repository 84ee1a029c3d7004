"""The numba inference rasterizer against the float64 reference and the differentiable rasterizer."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError, PoseError
from edmcgs.geometry import Intrinsics
from edmcgs.model.render import reference
from edmcgs.model.render.rasterize import rasterize
from edmcgs.model.render.rasterize_fast import rasterize_fast
from harness.scenes import at_camera_depth, random_scene, with_values

FIELDS = ("means", "quats", "scales", "opacities", "colors")
BG = [0.1, 0.2, 0.3]
ROOT = Path(__file__).resolve().parents[2]


def fast(scene, background=None, **kw):
    return rasterize_fast(*(scene[n] for n in FIELDS), scene["w2c"], scene["intrinsics"],
                          background=background, return_alpha=True, return_depth=True, **kw)


def ref_render(scene, background=None, **kw):
    k = scene["intrinsics"]
    return reference.render(*(scene[n] for n in FIELDS), scene["w2c"], k.fx, k.fy, k.cx, k.cy, k.width,
                            k.height, background=background, **kw)


def assert_matches(out, ref, atol):
    assert out.image.dtype == np.float32 and out.alpha.dtype == np.float32
    np.testing.assert_allclose(out.image, ref[0], atol=atol, rtol=0)
    np.testing.assert_allclose(out.alpha, ref[1], atol=atol, rtol=0)
    np.testing.assert_allclose(out.depth, ref[2], atol=atol * 10, rtol=0)


@pytest.mark.parametrize("sh_degree, channels", [(None, 3), (None, 1), (0, 3), (1, 3), (2, 1), (3, 3)])
def test_matches_the_reference(sh_degree, channels):
    scene = random_scene(250, 61, 43, seed=30 + (sh_degree or 0), sh_degree=sh_degree, channels=channels)
    out = fast(scene, background=BG[:channels])
    assert out.image.shape == (43, 61, channels)
    assert_matches(out, ref_render(scene, background=BG[:channels]), 2e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_differentiable_rasterizer(seed):
    """The contract: <= 1e-3 max abs per pixel against ``rasterize`` (float32) on dense scenes."""
    scene = random_scene(3000, 120, 90, seed=40 + seed, sh_degree=3, px_sigma=(0.7, 5.0))
    out = fast(scene, background=BG)
    ref = rasterize(*(torch.tensor(scene[n], dtype=torch.float32) for n in FIELDS), scene["w2c"],
                    scene["intrinsics"], background=BG, return_alpha=True, return_depth=True)
    assert ref.alpha.mean() > 0.9  # dense: many layers per pixel
    np.testing.assert_allclose(out.image, ref.image.numpy(), atol=1e-3, rtol=0)
    np.testing.assert_allclose(out.alpha, ref.alpha.numpy(), atol=1e-3, rtol=0)
    np.testing.assert_allclose(out.depth, ref.depth.numpy(), atol=1e-2, rtol=0)


@pytest.mark.parametrize("alpha_min, t_min", [(0.0, 0.0), (0.05, 1e-4), (1 / 255, 0.3)])
def test_knobs_follow_the_same_math(alpha_min, t_min):
    scene = random_scene(200, 40, 30, seed=50, opacity=(0.5, 1.0))
    out = fast(scene, background=BG, alpha_min=alpha_min, t_min=t_min)
    assert_matches(out, ref_render(scene, background=BG, alpha_min=alpha_min, t_min=t_min), 2e-5)


def test_opaque_stacks_stop_at_the_transmittance_floor():
    scene = random_scene(400, 48, 40, seed=51, opacity=(0.9, 1.0), px_sigma=(4.0, 10.0))
    ref = ref_render(scene, background=BG)
    assert (ref[1] > 1 - 2e-4).mean() > 0.5
    assert_matches(fast(scene, background=BG), ref, 2e-5)


def test_behind_the_camera_and_in_front_of_the_near_plane():
    culled = [-3.0, -1e-9, 0.0, 0.5 * (1 - 1e-3)]
    scene = at_camera_depth(random_scene(40, 40, 30, seed=52), slice(0, 4), culled)
    scene = at_camera_depth(scene, slice(4, 6), [0.5 * (1 + 1e-3), 0.51])
    assert_matches(fast(scene, background=BG, near=0.5), ref_render(scene, background=BG, near=0.5), 2e-5)


def test_on_the_near_plane_is_finite_either_way():
    scene = at_camera_depth(random_scene(40, 40, 30, seed=52), slice(0, 3), [0.5] * 3)
    out = fast(scene, background=BG, near=0.5)
    assert all(np.isfinite(a).all() for a in (out.image, out.alpha, out.depth))
    assert out.image.min() >= 0 and out.image.max() <= 1 and out.alpha.max() <= 1 and out.depth.min() >= 0


@pytest.mark.parametrize("alpha_min", [0.0, 1 / 255])
def test_opacities_at_zero_and_at_the_floor(alpha_min):
    # every Gaussian is projected before the cull: log 0 = -inf must neither draw nor leak a NaN
    floor = 1 / 255
    scene = with_values(random_scene(40, 40, 30, seed=57),
                        opacities=(slice(0, 20), [0.0, floor, floor - 1e-7, floor + 1e-7] * 5))
    out = fast(scene, background=BG, alpha_min=alpha_min)
    assert all(np.isfinite(a).all() for a in (out.image, out.alpha, out.depth))
    assert_matches(out, ref_render(scene, background=BG, alpha_min=alpha_min), 2e-5)


@pytest.mark.parametrize("scale", [1e-8, 1e-3, 1.0, 1e3])
def test_extreme_scales(scale):
    scene = with_values(random_scene(30, 40, 30, seed=53), scales=(slice(0, 10), scale))
    scene = with_values(scene, scales=((slice(10, 15), 0), scale))
    assert_matches(fast(scene, background=BG), ref_render(scene, background=BG), 2e-5)


def test_flat_covariances_and_opacity_one():
    scene = random_scene(30, 40, 30, seed=54, px_sigma=(2.0, 5.0))
    scene = with_values(scene, scales=((slice(0, 10), 2), 0.0))
    scene = with_values(scene, scales=((slice(10, 20), slice(1, 3)), 0.0))
    scene = with_values(scene, scales=(slice(20, 25), 0.0), opacities=(slice(0, 15), 1.0))
    out = fast(scene, background=BG)
    assert_matches(out, ref_render(scene, background=BG), 2e-5)
    assert out.alpha.max() <= 1 - 1e-4 + 1e-6


@pytest.mark.parametrize("n", [0, 5])
def test_empty_or_fully_culled_scene_is_background(n):
    scene = random_scene(max(n, 1), 20, 10, seed=55)
    scene = {k: (v[:n] if k in FIELDS else v) for k, v in scene.items()}
    if n:
        scene = at_camera_depth(scene, slice(None), [-1.0] * n)
    out = fast(scene, background=BG)
    np.testing.assert_array_equal(out.image, np.broadcast_to(np.float32(BG), (10, 20, 3)))
    assert (out.alpha == 0).all() and (out.depth == 0).all()


@pytest.mark.parametrize("width, height", [(1, 1), (17, 1), (1, 23), (16, 16), (33, 2), (9, 40)])
def test_tiny_and_thin_images(width, height):
    scene = random_scene(50, width, height, seed=width * 31 + height, px_sigma=(0.5, 3.0), margin=1.0)
    out = fast(scene, background=BG)
    assert out.image.shape == (height, width, 3)
    assert_matches(out, ref_render(scene, background=BG), 2e-5)


def test_no_nan_from_wild_but_finite_inputs():
    rng = np.random.default_rng(56)
    n = 2000
    k = Intrinsics(50.0, 50.0, 15.5, 10.5, 32, 22)
    out = rasterize_fast(rng.normal(size=(n, 3)) * np.exp(rng.uniform(-20, 8, (n, 1))),
                         rng.normal(size=(n, 4)) * np.exp(rng.uniform(-30, 30, (n, 1))),
                         np.exp(rng.uniform(-25, 7, (n, 3))), rng.uniform(0, 1, n),
                         rng.normal(size=(n, 16, 3)), np.eye(4), k, return_alpha=True, return_depth=True,
                         near=1e-6)
    for a in (out.image, out.alpha, out.depth):
        assert np.isfinite(a).all()


def test_accepts_torch_tensors_and_other_float_dtypes():
    scene = random_scene(100, 30, 20, seed=57, sh_degree=1)
    base = fast(scene, background=BG)
    tensors = {n: torch.tensor(scene[n], requires_grad=True) for n in FIELDS}
    out = rasterize_fast(*tensors.values(), torch.tensor(scene["w2c"]), scene["intrinsics"],
                         background=torch.tensor(BG))
    np.testing.assert_array_equal(out.image, base.image)
    assert out.alpha is None and out.depth is None
    halves = {n: scene[n].astype(np.float16) for n in FIELDS}  # converted to float32 at the boundary
    assert rasterize_fast(*halves.values(), scene["w2c"], scene["intrinsics"]).image.dtype == np.float32


@pytest.mark.parametrize("name", FIELDS)
def test_non_finite_input_names_the_argument(name):
    scene = random_scene(5, 10, 8, seed=58)
    scene = with_values(scene, **{name: ((0,) * scene[name].ndim, np.inf)})
    with pytest.raises(InvalidInputError, match=f"{name} contains NaN or Inf"):
        fast(scene)


@pytest.mark.parametrize("bad", [{"means": ((1, 2), np.nan)}, {"colors": ((2, 0), -np.inf)},
                                 {"scales": ((3, 1), -1e-3)}, {"opacities": ((4,), 1.5)},
                                 {"opacities": ((0,), np.nan)},
                                 {"scales": ((0, 0), np.nan), "opacities": ((1,), -1.0)},
                                 {"quats": ((2,), 0.0)}])
def test_refuses_what_the_differentiable_path_refuses_with_its_message(bad):
    """The fast path checks the values in one numba pass: same checks, same order, same words."""
    scene = random_scene(6, 10, 8, seed=60, sh_degree=1)
    scene = with_values(scene, **bad)
    with pytest.raises(InvalidInputError) as slow:
        rasterize(*(torch.tensor(scene[n]) for n in FIELDS), scene["w2c"], scene["intrinsics"])
    with pytest.raises(InvalidInputError) as quick:
        fast(scene)
    assert str(quick.value) == str(slow.value)


def test_thread_count_changes_nothing_but_speed():
    scene = random_scene(500, 70, 50, seed=61, sh_degree=1)
    one = fast(scene, background=BG, threads=1)
    many = min(2, numba.config.NUMBA_NUM_THREADS)
    np.testing.assert_array_equal(fast(scene, background=BG, threads=many).image, one.image)
    np.testing.assert_array_equal(fast(scene, background=BG).image, one.image)
    with pytest.raises(InvalidInputError, match="threads"):
        fast(scene, threads=0)


def test_bad_arguments_are_named():
    scene = random_scene(5, 10, 8, seed=59)
    with pytest.raises(InvalidInputError, match="opacities must lie in"):
        fast(with_values(scene, opacities=(0, -0.5)))
    with pytest.raises(InvalidInputError, match="quats must have shape"):
        fast(dict(scene, quats=scene["quats"][:3]))
    with pytest.raises(InvalidInputError, match="means must be an array of numbers"):
        fast(dict(scene, means="not an array"))
    with pytest.raises(PoseError, match="w2c"):
        fast(dict(scene, w2c=np.full((4, 4), np.nan)))
    for knob in ("alpha_min", "t_min"):
        with pytest.raises(InvalidInputError, match=knob):
            fast(scene, **{knob: -0.1})
        with pytest.raises(InvalidInputError, match=knob):
            fast(scene, **{knob: float("nan")})


def test_a_new_process_loads_the_kernels_from_the_jit_cache():
    """The first render of a fresh process must not recompile: every kernel is a cache hit."""
    fast(random_scene(20, 20, 10, seed=60, sh_degree=2))  # make sure the cache is written
    script = (
        "import json, numpy as np\n"
        "from edmcgs.model.render import checks_fast, rasterize_fast as rf\n"
        "from edmcgs.geometry import Intrinsics\n"
        "rf.rasterize_fast(np.zeros((1, 3)) + [0, 0, 2], [[1, 0, 0, 0]], np.full((1, 3), .1), [.5],"
        " np.zeros((1, 9, 3)), np.eye(4), Intrinsics(10., 10., 4., 4., 9, 9))\n"
        "print(json.dumps({k: [sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]"
        " for k, f in (('checks', checks_fast._flags), ('project', rf._project), ('sh', rf._sh_colors),"
        " ('order', rf.depth_order),"
        " ('bin', rf.bin_tiles), ('blend', rf._blend))}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=300, check=True)
    stats = json.loads(done.stdout.strip().splitlines()[-1])
    for kernel, (hits, misses) in stats.items():
        assert hits >= 1 and misses == 0, (kernel, hits, misses)


@pytest.mark.parametrize("path", ["fast", "reference", "torch"])
def test_a_splat_reaches_every_pixel_its_alpha_does(path):
    """One splat alone, against its alpha evaluated at every pixel: no tile seam may cut it off. 3DGS's
    tile rule dropped the tile after mean + radius when that sum lay in the tile's first pixel unit,
    though that pixel row's alpha still reached 1/255 (gsplat's CUDA kernels keep it)."""
    from edmcgs.model.render.projection import ALPHA_MIN, ewa_project

    scene = random_scene(400, 70, 45, seed=11, opacity=(0.05, 0.34))
    one = {n: scene[n][74:75] for n in FIELDS} | {"w2c": scene["w2c"], "intrinsics": scene["intrinsics"]}
    k = scene["intrinsics"]
    if path == "fast":
        alpha = fast(one).alpha
    elif path == "reference":
        alpha = ref_render(one)[1]
    else:
        alpha = rasterize(*(torch.tensor(one[n], dtype=torch.float64) for n in FIELDS), one["w2c"], k,
                          return_alpha=True).alpha.numpy()
    p = ewa_project(*(torch.tensor(one[n], dtype=torch.float64) for n in ("means", "quats", "scales")),
                    torch.tensor(scene["w2c"]), k, 0.01)
    (mx, my), (a, b, c) = p.mean2d[0].numpy(), p.conic[0].numpy()
    y, x = np.mgrid[0:k.height, 0:k.width]
    dx, dy = x - mx, y - my
    q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
    want = np.minimum(0.99, one["opacities"][0] * np.exp(-0.5 * q))
    want[want < ALPHA_MIN] = 0
    ca, cb, cc = p.cov2d[0].numpy()
    radius = math.ceil(3 * math.sqrt(0.5 * (ca + cc) + math.sqrt(max(0.1, 0.25 * (ca - cc) ** 2 + cb * cb))))
    assert 16 <= my + radius < 17  # the case: mean + radius in the first pixel unit of tile row 1
    np.testing.assert_allclose(alpha, want, atol=1e-5, rtol=0)
