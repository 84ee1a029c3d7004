"""A final checkpoint and its train-state sidecar are one unit: a save stopped at any of its writes and
renames (a kill, a full disk) leaves a checkpoint whose own train state is found beside it."""

from __future__ import annotations

import errno
import os
import shutil

import pytest
import torch

import edmcgs.atomic
from edmcgs.errors import DiskFullError
from edmcgs.model.checkpoint import read_checkpoint
from edmcgs.model.train.resume import resume_state, save_final
from tests.support.models import TINY, build

STEPS = 10
"""The writes and renames of a final save: per file written (the staged state, the checkpoint) its
torch.save, fsync, rename and folder fsync; then the state's rename to the sidecar's name and a fsync."""


@pytest.fixture
def pair(tmp_path):
    """A folder holding a finished run's checkpoint and sidecar (step 4), and a newer model to save."""
    model, _ = build(TINY)
    folder = tmp_path / "pristine"
    folder.mkdir()
    old = save_final(model, folder / "run.ckpt", {"step": 4})
    with torch.no_grad():
        next(p for p in model.parameters() if p.is_floating_point()).add_(0.01)
    return folder, model, old


def _hooked(monkeypatch, at: int, fail) -> None:
    """Call ``fail(name, args)`` before the ``at``-th write or rename of the save (0-based)."""
    count = [0]

    def wrap(name, real):
        def hooked(*args, **kwargs):
            if count[0] == at:
                fail(name, args)
            count[0] += 1
            return real(*args, **kwargs)
        return hooked

    monkeypatch.setattr(torch, "save", wrap("save", torch.save))
    monkeypatch.setattr(edmcgs.atomic, "_fsync", wrap("fsync", edmcgs.atomic._fsync))
    monkeypatch.setattr(os, "replace", wrap("replace", os.replace))


def _consistent(folder, old: str) -> int:
    """The step of the train state a resume finds for the checkpoint on disk (4: the old one, 8: the new)."""
    payload = read_checkpoint(folder / "run.ckpt")
    state, _origin = resume_state(folder / "run.ckpt", payload)
    assert state is not None, "the checkpoint on disk lost its train state"
    assert state["step"] == (4 if payload["checksum"] == old else 8), "a train state of the other checkpoint"
    return state["step"]


def test_a_save_killed_at_any_step_leaves_a_resumable_pair(pair, tmp_path, monkeypatch):
    pristine, model, old = pair
    outcomes = []
    for at in range(STEPS + 1):
        folder = tmp_path / f"killed-{at}"
        shutil.copytree(pristine, folder)
        pid = os.fork()
        if pid == 0:  # the child dies as kill -9 would: no cleanup, no exception handler
            try:
                def die(name, args):
                    if name == "save":  # half the file written, then the kill
                        with open(args[1], "wb") as fh:
                            fh.write(b"PK\x03\x04 half a file")
                    os._exit(9)

                _hooked(monkeypatch, at, die)
                save_final(model, folder / "run.ckpt", {"step": 8})
            finally:
                os._exit(0)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == (9 if at < STEPS else 0), at
        outcomes.append(_consistent(folder, old))
    assert outcomes[0] == 4 and outcomes[-1] == 8 and outcomes == sorted(outcomes), outcomes


def test_a_full_disk_at_any_step_leaves_the_pair_and_says_so(pair, tmp_path, monkeypatch):
    pristine, model, old = pair
    for at in range(STEPS):
        folder = tmp_path / f"full-{at}"
        shutil.copytree(pristine, folder)

        def full(name, args):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        with monkeypatch.context() as patch:
            _hooked(patch, at, full)
            with pytest.raises((DiskFullError, OSError)) as info:
                save_final(model, folder / "run.ckpt", {"step": 8})
        if isinstance(info.value, DiskFullError):  # a write: named, in one line
            assert "no space left on device" in str(info.value) and "\n" not in str(info.value)
        step = _consistent(folder, old)
        left = sorted(p.name for p in folder.iterdir())
        if step == 4:  # nothing of the new save stays behind
            assert left == ["run.ckpt", "run.ckpt.train-state"], (at, left)
