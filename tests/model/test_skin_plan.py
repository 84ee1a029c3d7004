"""Inference skinning (``skin_plan``): the same Gaussians as the differentiable path, work done once."""

import numpy as np
import torch

from edmcgs.geometry import quat_to_rotmat, world_to_camera
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.motion.skin_plan import _skin_torch, build_plan, skin
from edmcgs.model.motion.skinning import lbs
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import build, perturb_prior


def reference(model, t_us, emap):
    """The training path: control_motion + lbs with weights recomputed (``state_at``)."""
    w2c = torch.as_tensor(world_to_camera(model.meta.trajectory.at(t_us)), dtype=torch.float32)
    with torch.no_grad():
        return model.state_at(model.meta.normalized_time(t_us),
                              None if emap is None else torch.as_tensor(emap), w2c)


def test_deform_matches_the_differentiable_path_to_float32_rounding():
    model, data = build()
    randomize_event_branch(model)
    perturb_prior(model)
    t = tiny_scene.T0 + 60_000
    emap = data.event_map(tiny_scene.T0 + 0, t)
    assert np.any(emap != 0)
    for events in (None, emap):
        fast, ref = model.deform(t, events), reference(model, t, events)
        assert (fast.means - ref.means).abs().max() < 1e-5 * float(model.extent)
        assert (fast.quats - ref.quats).abs().max() < 1e-5
        for f in ("scales", "opacities", "colors"):
            assert torch.equal(getattr(fast, f), getattr(ref, f))
    assert not torch.allclose(model.deform(t, emap).means, model.deform(t).means)  # the events moved it


def test_the_torch_blend_matches_lbs_on_any_device_path():
    """The regrouped affine blend (the GPU path of ``skin``) against ``lbs`` with random transforms."""
    gen = torch.Generator().manual_seed(0)
    n, m, k = 500, 20, 3
    means, quats = torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen)
    control = torch.randn(m, 3, generator=gen)
    rot = torch.nn.functional.normalize(torch.randn(m, 4, generator=gen), dim=-1)
    trans = torch.randn(m, 3, generator=gen)
    bind = torch.randint(0, m, (n, k), generator=gen)
    weights = torch.softmax(torch.randn(n, k, generator=gen), -1)
    canonical = GaussianState(means, quats, torch.ones(n, 3), torch.ones(n), torch.ones(n, 3))
    plan = build_plan(canonical, bind, weights, None, ())
    ref_means, ref_quats = lbs(means, quats, control, rot, trans, bind, weights)
    cpu = skin(plan, control, rot, trans)
    assert (cpu.means - ref_means).abs().max() < 1e-4 and (cpu.quats - ref_quats).abs().max() < 1e-5
    # the torch ops a GPU runs, here on the CPU
    rotm = quat_to_rotmat(rot)
    affine = torch.cat([rotm, (control + trans - (rotm @ control[..., None])[..., 0])[..., None]], -1)
    out = _skin_torch(plan, affine.reshape(-1, 12), rot)
    assert (out.means - ref_means).abs().max() < 1e-4 and (out.quats - ref_quats).abs().max() < 1e-5


def test_the_plan_is_built_once_and_rebuilt_when_a_parameter_changes():
    model, _ = build()
    t = tiny_scene.T0 + 50_000
    model.deform(t)
    plan = model.skin_plan()
    model.deform(t + 10)
    assert model.skin_plan() is plan
    with torch.no_grad():
        model.gaussians.opacity_logits.add_(1.0)  # an optimizer step: in place
    assert model.skin_plan() is not plan
    assert torch.equal(model.deform(t).opacities, torch.sigmoid(model.gaussians.opacity_logits))


def test_a_query_at_an_anchor_skips_the_event_branch():
    model, data = build()
    randomize_event_branch(model)
    t = tiny_scene.T0 + 100_000
    calls = []
    model.encoder.register_forward_hook(lambda *a: calls.append(1))
    emap = data.event_map(tiny_scene.T0 + 20_000, tiny_scene.T0 + 90_000)
    model.deform(t, emap)
    assert calls == []  # Phi never ran at the anchor
    model.deform(t + 1, emap)
    assert calls == [1]
