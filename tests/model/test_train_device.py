"""A training step on the path a GPU takes: what it reads back to the host (each read waits for the
device), and on a CUDA device, whole steps with each rasterizer."""

import pytest
import torch

from edmcgs.model.train.trainer import Trainer
from edmcgs.pipeline import build_config, new_model, open_recording, training_data
from harness.host_reads import HostReads
from harness.server import build_scene

SMALL = ["init_points=600", "num_control_points=48", "deform_from=0.0"]
PRESETS = {"demo": [*SMALL, "iterations=20", "densify_from=0.0", "densify_every=10"],
           "real": [*SMALL, "iterations=20"]}
"""The demo preset densifying, and the real one (background layer, anchor windows, the next anchor)."""
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path, _ = build_scene(tmp_path_factory.mktemp("scene"), width=64, height=48, duration_s=1.0,
                          init_points=600, control_points=48)
    return open_recording(path, progress=False)


def _trainer(recording, preset: str, device: str = "cpu", *, compile: bool = False) -> Trainer:
    cfg = build_config(preset, PRESETS[preset], recording)
    data = training_data(recording)
    return Trainer(new_model(data, cfg), data, device=device, progress=False, compile=compile)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_a_step_reads_the_device_once_outside_the_rasterizer(recording, preset, monkeypatch):
    """The step's own code (deformation, event branch, background layer, losses) reads one thing back:
    the loss with its terms. Besides: the torch compositor's tile plan reads its lists (model/render/),
    densification the counts it resizes the model by (once every densify_every steps), and torch's CPU
    optimizer its step counts (inside torch: not project code)."""
    monkeypatch.setenv("EDMCGS_RASTERIZER", "torch")
    trainer = _trainer(recording, preset)
    trainer.train_step()
    steps = 12  # one densification among them with the demo preset
    with HostReads() as reads:
        for _ in range(steps):
            trainer.train_step()
    outside = {site: n for site, n in reads.direct.items()
               if not site.startswith(("model/render/", "model/train/density.py"))}
    assert sum(outside.values()) == steps, outside
    assert all(site.startswith("model/train/trainer.py:") for site in outside), outside


@CUDA
@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_cuda_steps(recording, preset, backend, monkeypatch):
    """Whole steps on CUDA (auto: gsplat where installed) give finite losses and keep every tensor there."""
    monkeypatch.setenv("EDMCGS_RASTERIZER", backend)
    trainer = _trainer(recording, preset, "cuda")
    losses = [trainer.train_step()["loss"] for _ in range(12)]
    assert all(torch.isfinite(torch.tensor(losses)))
    assert all(p.device.type == "cuda" for p in trainer.model.parameters())
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_compiled_step_trains_as_the_default(recording, preset, device):
    """torch.compile's skinning, prior network and losses: the same steps (same draws), losses and
    gradients equal to float32 rounding (gradients within 1e-3 of each parameter's largest, where that is
    above 1e-6: the radii's are rounding-sized; parameters are not compared: Adam's first steps amplify
    such rounding)."""
    plain, compiled = _trainer(recording, preset, device), _trainer(recording, preset, device, compile=True)
    assert compiled.model.skinning is not plain.model.skinning
    assert compiled.model.prior.compiled_field is not None and plain.model.prior.compiled_field is None
    assert (compiled.model.compiled_event_motion is None) == (compiled.model.transition is None)
    assert compiled.photometric_loss is not plain.photometric_loss
    for step in range(3):
        a, b = plain.train_step(), compiled.train_step()
        assert a.keys() == b.keys()
        for key in a:
            assert b[key] == pytest.approx(a[key], rel=1e-3, abs=1e-6), key
        if step == 0:
            for p, q in zip(plain.model.parameters(), compiled.model.parameters(), strict=True):
                scale = 0.0 if p.grad is None else float(p.grad.to_dense().abs().max())  # rows: sparse
                if scale > 1e-6:
                    torch.testing.assert_close(q.grad.to_dense(), p.grad.to_dense(), rtol=0,
                                               atol=1e-3 * scale)
