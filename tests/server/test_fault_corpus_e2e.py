"""Damaged recordings served for real: each damage kind (truncation, bit flips, a zeroed range, damage
mid-stream) of an HDF5 and an AEDAT4 recording, generated here, ends either in a one-line refusal at
start-up or in a live server whose /healthz names the failure; never a traceback, never a hang."""

from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from harness.server import ServerProcess

DAMAGES = ("truncate_half", "truncate_tail", "flip_bits", "zero_range", "flip_mid_stream", "xor_block")
"""xor_block: 200 bytes inverted at 60 % of the file, the damage that made dv-processing's LZ4 decoder spin
holding the GIL (the whole server froze); each /healthz below must still answer within 5 s."""


def _damage(data: bytes, kind: str) -> bytes:
    out = bytearray(data)
    rng = np.random.default_rng(17)
    n = len(out)
    if kind == "truncate_half":
        return bytes(out[: n // 2])
    if kind == "truncate_tail":
        return bytes(out[: n - 4096])
    if kind == "flip_bits":
        for i in rng.integers(1024, n, 64):
            out[i] ^= 1 << int(rng.integers(0, 8))
    elif kind == "zero_range":
        out[n // 3: n // 3 + 8192] = bytes(8192)
    elif kind == "xor_block":
        at = int(n * 0.6)
        out[at: at + 200] = bytes(b ^ 0xFF for b in out[at: at + 200])
    else:  # damage to the second half only: the replay starts, then meets it
        for i in rng.integers(n // 2, n, 32):
            out[i] ^= 0xFF
    return bytes(out)


@pytest.fixture(scope="module")
def aedat_scene(scene_files, tmp_path_factory):
    from edmcgs.sensor.files.recording import read_recording
    from tests.support.recordings import write_aedat

    rec_path, ckpt = scene_files
    rec = read_recording(rec_path)
    path = tmp_path_factory.mktemp("aedat") / "scene.aedat4"
    write_aedat(path, rec.events, rec.anchors, rec.width, rec.height)
    return path, ckpt


def _serve_and_judge(recording, ckpt) -> str:
    srv = ServerProcess(["--replay", str(recording), "--checkpoint", str(ckpt), "--loop"])
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if srv.proc.poll() is not None:
                log = srv.log()
                assert srv.proc.returncode != 0
                assert "Traceback" not in log, log
                return "refused"
            try:
                health = httpx.get(srv.url + "/healthz", timeout=5)
                break
            except httpx.TransportError:
                time.sleep(0.3)
        else:
            pytest.fail(f"no answer in 120 s:\n{srv.log()}")
        # Live: let the replay run into the damage, then the server must still answer, saying why.
        for _ in range(20):
            health = httpx.get(srv.url + "/healthz", timeout=5)
            body = health.json()
            assert body["source"] != "stopped", body
            if body["source"] == "error":
                assert body["source_error"], body
                break
            time.sleep(0.25)
        assert httpx.get(srv.url + "/scene", timeout=10).status_code == 200
        assert "Traceback" not in srv.log()
        return body["source"]
    finally:
        srv.stop()


@pytest.mark.parametrize("kind", DAMAGES)
def test_damaged_hdf5_is_refused_or_reported(scene_files, tmp_path, kind):
    rec, ckpt = scene_files
    bad = tmp_path / "bad.h5"
    bad.write_bytes(_damage(rec.read_bytes(), kind))
    outcome = _serve_and_judge(bad, ckpt)
    print(f"{bad.suffix} {kind}: {outcome}")
    assert outcome in ("refused", "error", "streaming", "ended")


@pytest.mark.parametrize("kind", DAMAGES)
def test_damaged_aedat4_is_refused_or_reported(aedat_scene, tmp_path, kind):
    rec, ckpt = aedat_scene
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(_damage(rec.read_bytes(), kind))
    outcome = _serve_and_judge(bad, ckpt)
    print(f"{bad.suffix} {kind}: {outcome}")
    assert outcome in ("refused", "error", "streaming", "ended")
