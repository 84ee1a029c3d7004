"""Checkpoint and command-line fault cases of issue 17: each a clear one-line error, never a traceback."""

from __future__ import annotations

import os

import pytest
import torch

from edmcgs.errors import CheckpointError, InvalidInputError
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.devices import check_device


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo should-never-run",))


def test_issue17_8_malicious_pickle_never_suggests_weights_only_false(tmp_path):
    path = tmp_path / "evil.ckpt"
    torch.save({"format": "edmcgs-checkpoint", "x": _Evil()}, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert "weights_only" not in message and "\n" not in message
    assert "system" in message


def test_issue17_8_garbage_file_is_one_line(tmp_path):
    path = tmp_path / "junk.ckpt"
    path.write_bytes(b"PK\x03\x04" + b"\x00garbage" * 50)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert "weights_only" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["banana", "cuda" if not torch.cuda.is_available() else "cuda:99", "cuda:99",
                                  "tpu"])
def test_issue17_9_unavailable_devices_are_refused(name):
    with pytest.raises(InvalidInputError, match=r"available|unknown"):
        check_device(name)


def test_issue17_9_cpu_device_passes():
    assert check_device("cpu") == "cpu"
