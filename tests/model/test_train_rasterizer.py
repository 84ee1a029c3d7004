"""Training on the CPU differentiates the numba rasterizer; the torch one (EDMCGS_RASTERIZER=torch) gives
the trainer the same gradients, the screen-space ones densification reads included."""

import torch

from edmcgs.model.render.composite import Composite
from edmcgs.model.render.composite_fast import CompositeFast
from edmcgs.model.train.trainer import Trainer
from tests.support.models import TINY, build

CFG = TINY.replace(densify_from=0.0)  # densification statistics from the first step on


def _one_step(monkeypatch, backend):
    monkeypatch.setenv("EDMCGS_RASTERIZER", backend)
    calls = {"numba": 0, "torch": 0}
    for name, fn_cls in (("numba", CompositeFast), ("torch", Composite)):
        real = fn_cls.backward

        def spy(ctx, *grads, _real=real, _name=name):
            calls[_name] += 1
            return _real(ctx, *grads)

        monkeypatch.setattr(fn_cls, "backward", staticmethod(spy))
    model, data = build(CFG)
    with torch.no_grad():  # anisotropic, so that the rotations get gradients (isotropic ones have none)
        log_scales = model.gaussians.log_scales
        log_scales += 0.5 * torch.randn(log_scales.shape, generator=torch.Generator().manual_seed(0))
    trainer = Trainer(model, data, progress=False)
    trainer.train_step()
    g = model.gaussians
    names = ("means", "quats", "log_scales", "opacity_logits", "features")
    grads = {name: getattr(g, name).grad.clone() for name in names}
    return calls, grads, trainer.stats.total.clone()


def test_a_training_step_takes_the_numba_backward_and_matches_the_torch_one(monkeypatch):
    calls, grads, screen = _one_step(monkeypatch, "auto")
    assert calls["numba"] > 0 and calls["torch"] == 0
    ref_calls, ref_grads, ref_screen = _one_step(monkeypatch, "torch")
    assert ref_calls["torch"] > 0 and ref_calls["numba"] == 0
    for name, ref in ref_grads.items():
        assert torch.isfinite(grads[name]).all(), name
        err = float((grads[name] - ref).abs().max() / ref.abs().max())
        assert err < 1e-3, f"{name}: {err:.2e}"
    assert (screen > 0).sum() > 0.5 * screen.numel()
    assert float((screen - ref_screen).abs().max() / ref_screen.abs().max()) < 1e-3
