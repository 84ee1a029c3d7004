"""Tiny EdMCGS models for tests: the tiny preset, a model built on ``tiny_scene``, weights that make the
event branch and the prior do something, and the one-torch-thread fixture."""

import pytest
import torch

from edmcgs.model.config import preset
from edmcgs.model.dynamic import EdMCGS
from edmcgs.pipeline import new_model
from tests.support import tiny_scene

TINY = preset("demo").replace(init_points=600, num_control_points=32, deform_width=32, deform_depth=2,
                              iterations=40, substeps=4, max_pair_steps=4, eval_every=0, checkpoint_every=0,
                              densify_from=0.2, densify_every=10, densify_until=0.8, train_scale=1.0,
                              event_warmup=(0.0, 0.2))


def build(cfg=TINY, **kwargs) -> tuple[EdMCGS, object]:
    data = tiny_scene.data(**kwargs)
    model = new_model(data, cfg)
    return model, data


def states_equal(a, b) -> bool:
    fields = ("means", "quats", "scales", "opacities", "colors")
    return all(torch.equal(getattr(a, f), getattr(b, f)) for f in fields)


def perturb_prior(model, scale=0.3, seed=1):
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.prior.parameters():
            p.add_(torch.randn(p.shape, generator=gen) * scale)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Model tests run torch on one thread: on the shared 2-core CPU, OpenMP threads that spin-wait for
    each other make every render many times slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
