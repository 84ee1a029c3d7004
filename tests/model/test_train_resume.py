"""Stopping and continuing a run: the stop event, the final checkpoint's train-state sidecar, the resume
command line, a write cut short, and the TensorBoard curves."""

from __future__ import annotations

import math
import sys
import threading

import pytest
import torch

from edmcgs.cli import main
from edmcgs.errors import CheckpointError, InvalidInputError
from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
from edmcgs.model.train import curves
from edmcgs.model.train.resume import resume_state, sidecar_path, write_sidecar
from edmcgs.model.train.trainer import Trainer
from edmcgs.train_cli import resume_command
from tests.support.models import TINY, build
from tests.support.recordings import TINY_TRAIN_SETS, write_tiny_h5

CFG = TINY.replace(iterations=8, densify_from=0.9)


def test_a_set_stop_event_ends_fit_after_the_step_with_a_resumable_checkpoint(tmp_path):
    model, data = build(CFG)
    trainer = Trainer(model, data, progress=False)
    stop = threading.Event()
    stop.set()
    path = tmp_path / "run.ckpt"
    trainer.fit(path, stop=stop)
    assert trainer.interrupted and trainer.step == 1
    assert read_checkpoint(path)["train_state"]["step"] == 1
    assert not sidecar_path(path).exists()


def test_a_final_checkpoint_keeps_its_train_state_beside_it(tmp_path):
    model, data = build(CFG)
    trainer = Trainer(model, data, progress=False)
    path = tmp_path / "run.ckpt"
    trainer.fit(path)
    payload = read_checkpoint(path)
    assert payload["train_state"] is None and not trainer.interrupted
    state, origin = resume_state(path, payload)
    assert state["step"] == 8 and "run.ckpt.train-state" in origin
    # Past the schedule: its end values, and the same two steps as a run that did not stop.
    resumed = Trainer(load_checkpoint(path), data, progress=False)
    resumed.load_train_state(state)
    resumed.fit(path, until=10)
    assert resumed.step == 10 and resume_state(path, read_checkpoint(path))[0]["step"] == 10
    for group in resumed.optimizer.param_groups:
        if group["name"] == "means":
            assert group["lr"] == pytest.approx(CFG.lr_means * float(resumed.model.extent) * 0.01)
    straight_model, _ = build(CFG)
    straight = Trainer(straight_model, data, progress=False)
    straight.fit(until=10)
    for (name, a), b in zip(resumed.model.state_dict().items(), straight.model.state_dict().values(),
                            strict=True):
        if a.is_floating_point():
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-6), name
    # A mid-training checkpoint over it carries its own state: the sidecar no longer belongs, and goes.
    resumed.save_resumable(path)
    assert not sidecar_path(path).exists()


def test_a_sidecar_of_another_checkpoint_or_damaged_is_refused(tmp_path):
    model, _ = build(CFG)
    path = tmp_path / "run.ckpt"
    digest = save_checkpoint(model, path)
    assert resume_state(path, read_checkpoint(path))[0] is None  # no sidecar: a fresh optimizer
    write_sidecar(path, {"step": 5}, "0" * 64)
    with pytest.raises(CheckpointError, match=r"belongs to another version .* remove"):
        resume_state(path, read_checkpoint(path))
    write_sidecar(path, {"step": 5}, digest)
    assert resume_state(path, read_checkpoint(path))[0] == {"step": 5}
    sidecar_path(path).write_bytes(b"cut")
    with pytest.raises(CheckpointError, match="truncated, damaged or not a train-state file"):
        resume_state(path, read_checkpoint(path))


def test_a_checkpoint_write_cut_short_by_ctrl_c_leaves_nothing_partial(tmp_path, monkeypatch):
    model, _ = build(CFG)
    path = tmp_path / "run.ckpt"
    save_checkpoint(model, path)
    before = path.read_bytes()

    def interrupted(payload, f):  # half a file, then the second Ctrl-C
        with open(f, "wb") as fh:
            fh.write(b"PK\x03\x04 half")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(model, path, train_state={"step": 3})
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["run.ckpt"]


def test_resume_command_replaces_its_own_resume_and_steps():
    argv = ["rec.h5", "-o", "out dir/a.ckpt", "--resume", "--set", "x=1", "--steps=4", "--steps", "7",
            "--resume", "old.ckpt", "-q"]
    assert resume_command(argv, "out dir/a.ckpt", None) == \
        "edmcgs train rec.h5 -o 'out dir/a.ckpt' --set x=1 -q --resume 'out dir/a.ckpt'"
    assert resume_command(["r", "-o", "a", "--resume=b"], "a", 12).endswith("-o a --resume a --steps 12")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_tiny_h5(tmp_path_factory.mktemp("rec") / "tiny.h5")


def _train(recording, ckpt, *extra):
    sets = [*TINY_TRAIN_SETS, "iterations=4", "eval_every=2", "checkpoint_every=0"]
    return main(["train", str(recording), "-o", str(ckpt), "--quiet", *extra,
                 *[a for s in sets for a in ("--set", s)]])


def test_resume_a_final_checkpoint_with_more_steps(recording, tmp_path, capsys):
    ckpt = tmp_path / "run.ckpt"
    assert _train(recording, ckpt) == 0
    assert _train(recording, ckpt, "--resume") == 1
    assert "already at step 4 of 4: give --steps N" in capsys.readouterr().err
    other = tmp_path / "more.ckpt"
    assert _train(recording, other, "--resume", str(ckpt), "--steps", "2") == 0
    assert f"resuming from {ckpt} with the optimizer state in run.ckpt.train-state, at step 4" \
        in capsys.readouterr().out
    assert resume_state(other, read_checkpoint(other))[0]["step"] == 6
    assert _train(recording, tmp_path / "x.ckpt", "--resume", str(tmp_path / "absent.ckpt")) == 1
    assert "does not exist" in capsys.readouterr().err


def test_tensorboard_curves_are_read_back(recording, tmp_path):
    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = tmp_path / "tb"
    assert _train(recording, tmp_path / "run.ckpt", "--tensorboard", str(tb)) == 0
    acc = EventAccumulator(str(tb))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"train/loss", "train/photo", "train/gaussians", "train/step_seconds", "heldout/psnr",
            "heldout/ssim"} <= tags
    assert [e.step for e in acc.Scalars("train/loss")] == [1, 2, 3, 4]
    assert [e.step for e in acc.Scalars("heldout/psnr")] == [2, 4]
    assert all(math.isfinite(e.value) and e.value > 0 for e in acc.Scalars("heldout/psnr"))
    assert acc.Scalars("train/gaussians")[-1].value == len(load_checkpoint(tmp_path / "run.ckpt").gaussians)


def test_tensorboard_flag_without_the_extra_names_the_install_command(recording, tmp_path, monkeypatch,
                                                                      capsys):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # import fails as if not installed
    assert curves.tensorboard_missing() is not None
    with pytest.raises(InvalidInputError, match=r"pip install 'edmcgs\[tensorboard\]'"):
        curves.TensorBoardCurves(tmp_path / "tb")
    assert _train(recording, tmp_path / "run.ckpt", "--tensorboard", str(tmp_path / "tb")) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pip install 'edmcgs[tensorboard]'" in err
    assert not (tmp_path / "run.ckpt").exists()
