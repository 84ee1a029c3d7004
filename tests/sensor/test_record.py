import numpy as np
import pytest

from edmcgs.cli import main as edmcgs_main
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import read_recording, write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.record import main, record
from edmcgs.sensor.sources.aedat import AedatReplay
from edmcgs.sensor.sources.hdf5 import Hdf5Replay
from edmcgs.sensor.sources.pacing import Pacing
from tests.support.recordings import DVX_EVENTS, DVX_IMU, DVX_SENSOR, write_aedat

from .conftest import make_events, make_recording


def _events_and_frames(src):
    batches = list(src)
    frames = [b.frames for b in batches if b.frames is not None]
    return Events.concat([b.events for b in batches]), (Frames.concat(frames) if frames else None)


def test_dvxplorer_to_hdf5_through_the_edmcgs_command(tmp_path, dvxplorer_path, capsys):
    out = tmp_path / "p.h5"
    assert edmcgs_main(["record", str(dvxplorer_path), "-o", str(out), "--quiet"]) == 0
    assert f"{DVX_EVENTS} events" in capsys.readouterr().out
    rec = read_recording(out)
    with AedatReplay(dvxplorer_path, Pacing(factor=0)) as src:
        ev, _ = _events_and_frames(src)
    assert rec.events == ev and (rec.width, rec.height) == (320, 240) and rec.sensor == DVX_SENSOR
    assert len(rec.anchors) == 0 and rec.metadata["recorded_by"] == "edmcgs record"
    assert rec.metadata["source_stats"]["dropped"] == 0
    assert [p.name for p in tmp_path.iterdir()] == ["p.h5"]


def test_events_frames_and_imu_survive_every_conversion(tmp_path, dvxplorer_path):
    w, h = 346, 260
    ev = make_events(20_000, w, h, rate_hz=1e5)
    frames = Frames(np.linspace(ev.t_start, ev.t_end, 5).astype(np.int64),
                    np.random.default_rng(1).integers(0, 256, (5, h, w, 3), dtype=np.uint8))
    src = write_aedat(tmp_path / "src.aedat4", ev, frames, w, h)
    assert main([str(src), "-o", str(tmp_path / "a.h5"), "--quiet"]) == 0
    rec = read_recording(tmp_path / "a.h5")
    assert rec.events == ev and rec.anchors == frames
    assert main([str(tmp_path / "a.h5"), "-o", str(tmp_path / "b.aedat4"), "--quiet"]) == 0
    with AedatReplay(tmp_path / "b.aedat4", Pacing(factor=0)) as replay:
        ev2, fr2 = _events_and_frames(replay)
        assert replay.info.frame_size == (w, h)
    assert ev2 == ev and fr2 == frames
    assert main([str(dvxplorer_path), "-o", str(tmp_path / "c.aedat4"), "--quiet"]) == 0
    imu = []
    for path in (dvxplorer_path, tmp_path / "c.aedat4"):
        with AedatReplay(path, Pacing(factor=0)) as replay:
            imu.append(np.concatenate([b.imu for b in replay if b.imu is not None]))
    assert len(imu[1]) == DVX_IMU
    np.testing.assert_array_equal(imu[0], imu[1])


def test_duration_and_start(tmp_path):
    rec = make_recording(n_events=50_000)
    path = write_recording(tmp_path / "r.h5", rec)
    t0 = rec.events.t_start
    args = [str(path), "-o", str(tmp_path / "d.h5"), "--start", "0.01", "--duration", "0.02", "--quiet"]
    assert main(args) == 0
    got = read_recording(tmp_path / "d.h5").events
    first = rec.events.time_slice(t0 + 10_000, 2**62).t_start
    assert got == rec.events.time_slice(first, first + 20_000)


def test_command_line_errors(tmp_path, capsys):
    out = tmp_path / "exists.h5"
    out.write_bytes(b"keep me")
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path / "x.h5"), "-o", str(out)])
    assert exc.value.code == 2 and "use --force" in capsys.readouterr().err and out.read_bytes() == b"keep me"
    with pytest.raises(SystemExit):
        main(["-o", str(tmp_path / "y.h5")])  # neither a source nor --live
    assert main([str(tmp_path / "missing.h5"), "-o", str(tmp_path / "y.h5"), "--quiet"]) == 1
    assert "no such file" in capsys.readouterr().err
    rec = write_recording(tmp_path / "r.h5", make_recording(n_events=100))
    assert main([str(rec), "-o", str(tmp_path / "y.mp4"), "--quiet"]) == 1
    assert "expected a name ending in" in capsys.readouterr().err
    assert main(["--live", "-o", str(tmp_path / "live.h5"), "--quiet"]) == 1  # no camera on this machine
    err = capsys.readouterr().err
    assert "libusb-1.0" in err or "0x152a" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exists.h5", "r.h5"]


class _Interrupting:
    """A real replay that fails after a few batches, as Ctrl-C or a crash would."""

    def __init__(self, inner, after, exc):
        self.inner, self.after, self.exc = inner, after, exc

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def read(self):
        self.after -= 1
        if self.after < 0:
            raise self.exc
        return self.inner.read()


def test_ctrl_c_keeps_what_was_recorded_and_a_crash_leaves_nothing(tmp_path):
    rec = make_recording(n_events=50_000)
    path = write_recording(tmp_path / "r.h5", rec)
    with Hdf5Replay(path, Pacing(factor=0)) as src:
        summary = record(_Interrupting(src, 2, KeyboardInterrupt()), tmp_path / "k.h5", progress=False)
    assert summary["interrupted"] and 0 < summary["events"] < len(rec.events)
    kept = read_recording(tmp_path / "k.h5").events
    assert kept == rec.events[:len(kept)]
    with Hdf5Replay(path, Pacing(factor=0)) as src, pytest.raises(RuntimeError, match="disk on fire"):
        record(_Interrupting(src, 2, RuntimeError("disk on fire")), tmp_path / "crash.aedat4", progress=False)
    with Hdf5Replay(path, Pacing(factor=0)) as src, pytest.raises(RuntimeError):
        record(_Interrupting(src, 2, RuntimeError("again")), tmp_path / "crash.h5", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.h5", "r.h5"]
