"""``edmcgs train`` in a real process stopped by SIGINT (Ctrl-C): a resumable checkpoint, the command to
continue, exit status 130; the continued run takes up the same losses an uninterrupted run has."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
from edmcgs.model.train.resume import resume_state, sidecar_path
from tests.support.recordings import TINY_TRAIN_SETS, write_tiny_h5

HAVE_TENSORBOARD = importlib.util.find_spec("tensorboard") is not None
"""Without the extra the loss curves are not compared (the parameters still are)."""

SETS = (*TINY_TRAIN_SETS, "iterations=100000", "eval_every=0", "checkpoint_every=3")
"""A schedule far longer than the test runs: only Ctrl-C or --steps ends it."""
CLI = [sys.executable, "-m", "edmcgs.cli"]


def _args(recording: Path, out: Path, tb: Path) -> list[str]:
    args = ["train", str(recording), "-o", str(out), "-q"] + (["--tensorboard", str(tb)] * HAVE_TENSORBOARD)
    return args + [a for s in SETS for a in ("--set", s)]


def _start(args: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([*CLI, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 240.0) -> None:
    """Until the periodic checkpoint exists: the training loop is running."""
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "training never wrote its periodic checkpoint"
        time.sleep(0.1)


def _losses(tb: Path) -> dict[int, float] | None:
    """train/loss by step, as TensorBoard reads it back (None without the extra)."""
    if not HAVE_TENSORBOARD:
        return None
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tb))
    acc.Reload()
    return {e.step: e.value for e in acc.Scalars("train/loss")}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_tiny_h5(tmp_path_factory.mktemp("rec") / "tiny.h5")


def test_ctrl_c_saves_a_checkpoint_that_resumes_where_it_stopped(recording, tmp_path):
    out, tb = tmp_path / "run.ckpt", tmp_path / "tb"
    proc = _start(_args(recording, out, tb), tmp_path)
    _wait_for(out, proc)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr
    line = next(ln for ln in stderr.splitlines() if "continue with: " in ln)
    assert f"saved a resumable checkpoint to {out}" in line
    stopped = read_checkpoint(out)["train_state"]["step"]
    assert stopped >= 3 and not list(tmp_path.glob(".*tmp-*"))
    losses = _losses(tb)
    assert losses is None or max(losses) == stopped

    # The printed command, run as printed (its own program name), continues for three more steps.
    command = shlex.split(line.split("continue with: ", 1)[1])
    assert command[:2] == ["edmcgs", "train"] and command[-2:] == ["--resume", str(out)]
    done = subprocess.run([*CLI, *command[1:], "--steps", "3"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"resuming from {out} with its optimizer state, at step {stopped}" in done.stdout
    payload = read_checkpoint(out)
    assert payload["train_state"] is None  # a final checkpoint: the train state is beside it
    state, origin = resume_state(out, payload)
    assert state["step"] == stopped + 3 and sidecar_path(out).name in origin
    resumed = _losses(tb)
    assert resumed is None or sorted(resumed) == list(range(1, stopped + 4))  # no step twice, none missing

    # The same steps without an interruption: the continued run takes up the very same losses.
    ref_out, ref_tb = tmp_path / "ref.ckpt", tmp_path / "ref_tb"
    ref = subprocess.run([*CLI, *_args(recording, ref_out, ref_tb), "--steps", str(stopped + 3)],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert ref.returncode == 0, ref.stderr
    reference = _losses(ref_tb)
    if reference is not None:
        assert sorted(reference) == sorted(resumed)
        for step in range(stopped + 1, stopped + 4):
            assert resumed[step] == pytest.approx(reference[step], rel=1e-4, abs=1e-6), step
    a, b = load_checkpoint(out), load_checkpoint(ref_out)
    assert len(a.gaussians) == len(b.gaussians)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        if x.is_floating_point():
            assert torch.allclose(x, y, rtol=1e-4, atol=1e-5), name


def test_a_second_ctrl_c_abandons_the_run_without_a_partial_file(recording, tmp_path):
    out, tb = tmp_path / "run.ckpt", tmp_path / "tb"
    proc = _start(_args(recording, out, tb), tmp_path)
    _wait_for(out, proc)
    proc.send_signal(signal.SIGINT)
    # The second as soon as the first is acknowledged: it lands in the step or in the save.
    deadline = time.monotonic() + 60
    while "Ctrl-C: finishing" not in (line := proc.stderr.readline()):
        assert line and time.monotonic() < deadline, "no acknowledgement of the first Ctrl-C"
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert not list(tmp_path.glob(".*tmp-*"))  # no partial file
    step = read_checkpoint(out)["train_state"]["step"]
    assert step >= 3  # the last complete checkpoint, whichever it is
    said = re.search(r"abandoned at step \d+; \S+ holds step (\d+)", stderr)
    assert said is None or int(said.group(1)) == step, stderr
