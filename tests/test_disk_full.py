"""A full disk while any tool writes its file: one line naming the file and "no space left on device"
(``DiskFullError``, raised by the one atomic writer), never a library's traceback; the file already at
the path stays as it was and nothing partial is left beside it.

The full disk is the kernel's own: each temporary file the writer is given is a link to /dev/full,
where every write fails with ENOSPC, whatever library writes (torch's C++ zip writer, h5py,
dv-processing, Pillow, plain Python)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import edmcgs.atomic
from edmcgs.errors import DiskFullError

pytestmark = pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
OLD = b"the file that was there before"


@pytest.fixture
def fill(monkeypatch):
    """Call it to fill the disk: every file written from then on fails with ENOSPC."""
    real = edmcgs.atomic.temp_path_for

    def on_full_disk(path: Path) -> Path:
        tmp = real(path)
        tmp.symlink_to("/dev/full")
        return tmp

    return lambda: monkeypatch.setattr(edmcgs.atomic, "temp_path_for", on_full_disk)


def _intact(target: Path) -> None:
    assert target.read_bytes() == OLD
    assert sorted(p.name for p in target.parent.iterdir() if p.name.startswith(".")) == [], "a partial file"


def _one_line_naming(text: str, target: Path) -> None:
    text = text.strip()
    assert "\n" not in text and "Traceback" not in text, text
    assert str(target) in text and "no space left on device" in text, text


@pytest.fixture
def model():
    from tests.support.models import build

    return build()[0]


def test_a_checkpoint(tmp_path, fill, model):
    from edmcgs.model.checkpoint import save_checkpoint

    target = tmp_path / "scene.ckpt"
    target.write_bytes(OLD)
    fill()
    with pytest.raises(DiskFullError) as info:
        save_checkpoint(model, target)
    _one_line_naming(str(info.value), target)
    _intact(target)


def test_a_training_history_report(tmp_path, fill):
    from edmcgs.model.train.trainer import write_history_csv

    target = tmp_path / "history.csv"
    target.write_bytes(OLD)
    fill()
    with pytest.raises(DiskFullError) as info:
        write_history_csv([{"step": 1, "psnr": 20.0, "ssim": 0.5, "frames": 2, "seconds": 1.0}], target)
    _one_line_naming(str(info.value), target)
    _intact(target)


def test_a_ply_export_command(tmp_path, fill, model, capsys):
    from edmcgs.cli import main
    from edmcgs.model.checkpoint import save_checkpoint

    ckpt = tmp_path / "in" / "scene.ckpt"
    save_checkpoint(model, ckpt)
    target = tmp_path / "scene.ply"
    target.write_bytes(OLD)
    fill()
    assert main(["export-ply", str(ckpt), "--t", "0.1", "-o", str(target), "--force", "-q"]) != 0
    _one_line_naming(capsys.readouterr().err, target)
    _intact(target)


@pytest.mark.parametrize("suffix", [".h5", ".aedat4"])
def test_a_recording_command(tmp_path, fill, suffix, capsys, monkeypatch):
    from edmcgs.cli import main
    from tests.support.recordings import write_tiny_h5

    (tmp_path / "in").mkdir()
    source = write_tiny_h5(tmp_path / "in" / "tiny.h5")
    target = tmp_path / f"copy{suffix}"
    target.write_bytes(OLD)
    if suffix == ".h5":
        fill()
    else:  # dv-processing's writer thread would abort the process: its disk is seen full before it writes
        real = os.statvfs

        def nearly_full(path):
            stat = real(path)
            if Path(path) != tmp_path:
                return stat
            return os.statvfs_result((stat.f_bsize, stat.f_frsize, stat.f_blocks, 10, 10, *tuple(stat)[5:]))

        monkeypatch.setattr(os, "statvfs", nearly_full)
    assert main(["record", str(source), "-o", str(target), "--force", "-q"]) != 0
    _one_line_naming(capsys.readouterr().err, target)
    _intact(target)


def test_a_video_export(tmp_path, fill):
    from edmcgs.clients.export import export_sweep

    class Client:  # a server's answers, enough for a sweep
        def scene(self):
            return {"t_start_us": 0, "t_end_us": 200_000}

        def render(self, **_):
            return np.zeros((8, 8, 3), np.uint8), {}

    target = tmp_path / "sweep.gif"
    target.write_bytes(OLD)
    fill()
    with pytest.raises(DiskFullError) as info:
        export_sweep(Client(), target, fps=10, progress=False)
    _one_line_naming(str(info.value), target)
    _intact(target)


def test_a_failure_on_a_disk_with_room_is_left_as_it_was(tmp_path):
    target = tmp_path / "x.bin"
    with pytest.raises(ValueError, match="not the disk"), edmcgs.atomic.atomic_output(target) as tmp:
        tmp.write_bytes(b"part")
        raise ValueError("not the disk")
    assert list(tmp_path.iterdir()) == []
