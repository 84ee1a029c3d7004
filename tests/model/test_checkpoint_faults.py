"""Checkpoint and command-line faults: each a clear one-line error, never a traceback."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from edmcgs.errors import CheckpointError, InvalidInputError
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.devices import check_device


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo should-never-run",))


def test_malicious_pickle_never_suggests_weights_only_false(tmp_path):
    path = tmp_path / "evil.ckpt"
    torch.save({"format": "edmcgs-checkpoint", "x": _Evil()}, path)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    message = str(info.value)
    assert "weights_only" not in message and "\n" not in message
    assert "system" in message


def test_garbage_file_is_one_line(tmp_path):
    path = tmp_path / "junk.ckpt"
    path.write_bytes(b"PK\x03\x04" + b"\x00garbage" * 50)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert "weights_only" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("name", ["banana", "cuda" if not torch.cuda.is_available() else "cuda:99", "cuda:99",
                                  "tpu"])
def test_unavailable_devices_are_refused(name):
    with pytest.raises(InvalidInputError, match=r"available|unknown"):
        check_device(name)


def test_cpu_device_passes():
    assert check_device("cpu") == "cpu"


# ----------------------------------------------------------------- malformed and damaged checkpoints

@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    from edmcgs.model.checkpoint import save_checkpoint
    from tests.support.models import build

    model, _data = build()
    path = tmp_path_factory.mktemp("ckpt") / "tiny.ckpt"
    save_checkpoint(model, path)
    return path


def _mutated(saved, tmp_path, mutate, *, keep_checksum=False):
    from edmcgs.model.checkpoint import checksum

    payload = torch.load(saved, weights_only=True)
    mutate(payload)
    if not keep_checksum:
        payload["checksum"] = checksum(payload)  # a malformed but consistently written file
    out = tmp_path / "bad.ckpt"
    torch.save(payload, out)
    return out


def _set(path, value):
    def mutate(payload):
        node = payload
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return mutate


MALFORMED = {
    "anchors_list": (_set(("meta", "anchors_us"), [1, 2, 3]), "anchors_us"),
    "anchors_empty": (_set(("meta", "anchors_us"), torch.zeros(0, dtype=torch.int64)), "anchors_us"),
    "huge_camera": (_set(("meta", "intrinsics", "width"), 200_000), "width"),
    "huge_camera_both": (lambda p: (p["meta"]["intrinsics"].update(width=200_000, height=200_000)), "width"),
    "huge_event_map": (_set(("meta", "event_width"), 10**9), "event_width"),
    "end_before_start": (lambda p: p["meta"].update(t_end_us=p["meta"]["t_start_us"] - 1), "t_end_us"),
    "step_string": (_set(("train_state",), {"step": "x", "optimizer": {}, "stats": {}, "rng": {},
                                             "generator": torch.zeros(1)}), "train_state.step"),
    "channels_7": (_set(("meta", "channels"), 7), "channels"),
    "fx_nan": (_set(("meta", "intrinsics", "fx"), float("nan")), "fx"),
    "sizes_string": (_set(("sizes", "num_gaussians"), "many"), "num_gaussians"),
    "anchors_unsorted": (lambda p: p["meta"].update(anchors_us=p["meta"]["anchors_us"].flip(0)),
                         "anchors_us"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_checkpoint_is_one_line_naming_the_field(saved, tmp_path, case):
    mutate, field = MALFORMED[case]
    path = _mutated(saved, tmp_path, mutate)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert field in str(info.value) and "\n" not in str(info.value)


def test_out_of_range_index_tensor_is_refused(saved, tmp_path):
    def flip(payload):
        bind = payload["state_dict"]["control.bind"]
        bind.view(-1)[0] = bind.view(-1)[0] ^ (1 << 40)  # a flipped high bit of an index
    path = _mutated(saved, tmp_path, flip)
    with pytest.raises(CheckpointError, match=r"control\.bind"):
        load_checkpoint(path)


@pytest.mark.parametrize("key", ["gaussians.means", "control.bind", "meta"])
def test_flipped_bit_is_detected_by_the_checksum(saved, tmp_path, key):
    def flip(payload):
        t = payload["meta"]["anchors_us"] if key == "meta" else payload["state_dict"][key]
        raw = t.view(-1).view(torch.uint8) if t.dtype != torch.int64 else t.view(-1)
        raw[0] = raw[0] ^ 1
    path = _mutated(saved, tmp_path, flip, keep_checksum=True)
    with pytest.raises(CheckpointError, match="checksum"):
        load_checkpoint(path)


@pytest.mark.parametrize("damage", ["truncate", "zero_range", "flip_bytes"])
def test_damaged_file_bytes_are_one_line(saved, tmp_path, damage):
    data = bytearray(saved.read_bytes())
    rng = np.random.default_rng(0)
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "zero_range":
        data[len(data) // 3: len(data) // 3 + 4096] = bytes(4096)
    else:
        for i in rng.integers(0, len(data), 16):
            data[i] ^= 0x10
    path = tmp_path / "damaged.ckpt"
    path.write_bytes(bytes(data))
    try:
        load_checkpoint(path)
    except CheckpointError as exc:
        assert "\n" not in str(exc) and "weights_only" not in str(exc)
    # loading without an error is allowed only when the damage missed every byte that matters


def test_valid_checkpoint_still_loads(saved):
    assert load_checkpoint(saved) is not None
