"""What a file is, by its first bytes; and every command says a wrong file, a busy port or a mistyped
config key before it imports torch, naming a recording given as a checkpoint and the reverse."""

import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import zipfile

import pytest

from edmcgs.errors import CheckpointError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording, sniff
from edmcgs.server import demo

CKPT, REC = demo.files()


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The demo's checkpoint and recording, and wrong or damaged files beside them."""
    d = tmp_path_factory.mktemp("kinds")
    data = CKPT.read_bytes()
    written = {"png": ("x.png", b"\x89PNG\r\n\x1a\n" + bytes(64)),
               "truncated": ("half.ckpt", data[: len(data) // 2]),
               "flipped": ("flipped.ckpt", _flip_in_largest_member(data)),
               "empty": ("empty.h5", b""),
               "aedat": ("a.aedat4", b"#!AER-DAT4.0\r\n" + bytes(64)),
               "userblock": ("ub.h5", bytes(512) + REC.read_bytes())}  # HDF5 after a 512-byte user block
    out = {"ckpt": CKPT, "rec": REC, "missing": d / "missing.h5", "zip": d / "plain.ckpt",
           "renamed": d / "scene.data"}
    for key, (name, content) in written.items():
        out[key] = d / name
        out[key].write_bytes(content)
    with zipfile.ZipFile(out["zip"], "w") as z:
        z.writestr("readme.txt", "not a torch file")
    shutil.copyfile(REC, out["renamed"])
    return out


def _flip_in_largest_member(data: bytes) -> bytes:
    """One flipped bit inside the largest stored tensor: the zip's structure intact, its CRC not."""
    import io

    with zipfile.ZipFile(io.BytesIO(data)) as z:
        info = max(z.infolist(), key=lambda i: i.file_size)
    name_len, extra_len = struct.unpack("<HH", data[info.header_offset + 26: info.header_offset + 30])
    at = info.header_offset + 30 + name_len + extra_len + info.file_size // 2
    out = bytearray(data)
    out[at] ^= 0x01
    return bytes(out)


def test_sniff_tells_each_kind(files):
    kinds = {k: sniff(files[k]) for k in ("ckpt", "rec", "png", "empty", "zip", "aedat", "userblock",
                                           "truncated")}
    assert kinds == {"ckpt": "checkpoint", "rec": "hdf5", "png": "png", "empty": "empty", "zip": "zip",
                     "aedat": "aedat4", "userblock": "hdf5", "truncated": "zip"}


def test_check_recording(files):
    assert check_recording(files["rec"]) == REC
    assert check_recording(files["userblock"]) == files["userblock"]
    assert check_recording(files["renamed"]) == files["renamed"]  # told by its content, not its name
    cases = {"missing": "no such file", "png": "is not a recording read here (a PNG image)",
             "empty": "(an empty file)", "ckpt": "is a checkpoint (a torch file), not a recording: HINT"}
    for key, said in cases.items():
        with pytest.raises(InvalidInputError) as info:
            check_recording(files[key], hint="HINT")
        assert said in str(info.value) and "\n" not in str(info.value), key


def test_check_checkpoint(files):
    assert check_checkpoint(CKPT, verify=True) == CKPT
    assert check_checkpoint(files["flipped"]) == files["flipped"]  # the CRCs are read only when verifying
    cases = {"missing": "does not exist", "rec": "is an HDF5 recording, not a checkpoint: HINT",
             "aedat": "is an AEDAT4 recording, not a checkpoint: HINT", "png": "(a PNG image)",
             "truncated": "truncated or not a torch file", "zip": "a zip archive, not a torch file",
             "flipped": "does not match its CRC"}
    for key, said in cases.items():
        with pytest.raises(CheckpointError) as info:
            check_checkpoint(files[key], hint="HINT", verify=True)
        assert said in str(info.value) and "\n" not in str(info.value), key


def test_loading_a_recording_as_a_checkpoint_names_it():
    from edmcgs.model.checkpoint import load_checkpoint

    with pytest.raises(CheckpointError, match="is an HDF5 recording, not a checkpoint"):
        load_checkpoint(REC)


# Each command in one fresh interpreter, in process: its exit code, its last stderr line and the heavy
# packages imported by then (none may be: the checks come before torch, numba and h5py).
_RUN = r"""
import contextlib, io, json, sys
from edmcgs.cli import main as edmcgs
from edmcgs.server.cli import main as serve
out = []
for name, argv in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            code = serve(argv) if name == "serve" else edmcgs([name, *argv])
        except SystemExit as exc:
            code = exc.code
    lines = err.getvalue().strip().splitlines() or [""]
    out.append([code, lines[-1], [m for m in ("torch", "numba", "h5py") if m in sys.modules]])
print(json.dumps(out))
"""


def test_commands_say_a_wrong_file_or_busy_port_before_importing_torch(files, tmp_path):
    f = {k: str(v) for k, v in files.items()}
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        cases = [
            (("train", [f["missing"], "-o", str(tmp_path / "o.ckpt")]), "missing.h5: no such file"),
            (("train", [f["ckpt"], "-o", str(tmp_path / "o.ckpt")]),
             "a checkpoint (a torch file), not a recording: edmcgs train takes the recording"),
            (("train", [f["rec"], "-o", str(tmp_path / "o.ckpt"), "--resume", f["rec"]]),
             "an HDF5 recording, not a checkpoint: --resume takes"),
            (("train", [f["rec"], "-o", str(tmp_path / "o.ckpt"), "--set", "iteration=5"]),
             "unknown key 'iteration'; did you mean 'iterations'?"),
            (("eval", [f["rec"], f["ckpt"]]), "not a checkpoint: edmcgs eval takes the checkpoint first"),
            (("export-ply", [f["rec"], "--t", "0", "-o", str(tmp_path / "x.ply")]), "not a checkpoint"),
            (("serve", ["--replay", f["png"], "--checkpoint", f["ckpt"], "--port", "0"]),
             "x.png is not a recording read here (a PNG image)"),
            (("serve", ["--replay", f["rec"], "--checkpoint", f["rec"], "--port", "0"]),
             "is an HDF5 recording, not a checkpoint: pass it as --replay"),
            (("serve", ["--replay", f["ckpt"], "--checkpoint", f["ckpt"], "--port", "0"]),
             "not a recording: pass it as --checkpoint"),
            (("serve", ["--replay", f["rec"], "--checkpoint", f["truncated"], "--port", "0"]), "truncated"),
            (("serve", ["--replay", f["rec"], "--checkpoint", f["flipped"], "--port", "0"]),
             "does not match its CRC"),
            (("serve", ["--port", port]), f"port {port} on 127.0.0.1 is in use"),
        ]
        env = {k: v for k, v in os.environ.items() if not k.startswith("EDMCGS_")}
        done = subprocess.run([sys.executable, "-c", _RUN, json.dumps([c for c, _ in cases])], env=env,
                              capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout)
    for ((name, argv), said), (code, line, heavy) in zip(cases, results, strict=True):
        assert code == 1 and said in line, (name, argv, line)
        assert heavy == [], (name, argv, heavy)
