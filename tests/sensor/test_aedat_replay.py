import threading

import dv_processing as dv
import numpy as np
import pytest

from edmcgs.errors import InvalidInputError, ReplayFormatError, SensorError
from edmcgs.sensor.events import Events
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.aedat import AedatReplay
from edmcgs.sensor.sources.base import EventSource
from edmcgs.sensor.sources.open import open_source
from edmcgs.sensor.sources.pacing import Pacer, Pacing
from tests.support.recordings import DVX_EVENTS, DVX_FIRST_US, DVX_IMU, DVX_LAST_US, DVX_SENSOR, write_aedat

from .conftest import make_events

FIRST_US, LAST_US = DVX_FIRST_US, DVX_LAST_US


def _drain(src):
    batches = list(src)
    events = Events.concat([b.events for b in batches])
    frames = [b.frames for b in batches if b.frames is not None]
    return batches, events, (Frames.concat(frames) if frames else None)


def test_a_dvxplorer_recording_replays_whole(dvxplorer_path):
    with AedatReplay(dvxplorer_path, Pacing(factor=0)) as src:
        assert isinstance(src, EventSource)
        info = src.info
        assert (info.width, info.height) == (320, 240)
        assert info.sensor == DVX_SENSOR and not info.has_frames and info.has_imu and not info.live
        assert info.t_range_us == (FIRST_US, LAST_US)
        batches, ev, frames = _drain(src)
        assert src.stats.dropped == 0 and src.stats.received == DVX_EVENTS
    assert len(ev) == DVX_EVENTS and frames is None
    assert (ev.t_start, ev.t_end) == (FIRST_US, LAST_US)
    assert round(100 * np.mean(ev.p > 0)) == 49
    assert sum(len(b.imu) for b in batches if b.imu is not None) == DVX_IMU
    # every batch is a 10 ms window, marked complete up to its end, and holds only its own events
    for b in batches:
        assert len(b.events) == 0 or (b.t_end_us - 10_000 <= b.events.t_start and b.events.t_end < b.t_end_us)
    assert batches[-1].t_end_us == LAST_US + 1
    # the same events dv-processing itself reads
    rec = dv.io.MonoCameraRecording(str(dvxplorer_path))
    raw = []
    while (store := rec.getNextEventBatch()) is not None:
        raw.append(store.numpy())
    raw = np.concatenate(raw)
    np.testing.assert_array_equal(ev.t, raw["timestamp"])
    np.testing.assert_array_equal(ev.x, raw["x"])
    np.testing.assert_array_equal(ev.p, np.where(raw["polarity"] > 0, 1, -1))


def test_events_and_frames_round_trip_exactly(tmp_path):
    w, h = 346, 260
    ev = make_events(30_000, w, h, rate_hz=2e5)
    rng = np.random.default_rng(3)
    t_f = np.linspace(ev.t_start, ev.t_end, 6).astype(np.int64)
    grey = Frames(t_f, rng.integers(0, 256, (6, h, w, 1), dtype=np.uint8))
    path = write_aedat(tmp_path / "grey.aedat4", ev, grey, w, h)
    with open_source(path, pacing=Pacing(factor=0, batch_us=7_000)) as src:
        assert src.info.has_frames and src.info.frame_size == (w, h) and src.info.sensor == "DAVIS346_test"
        _, ev2, fr2 = _drain(src)
    assert ev2 == ev and fr2 == grey
    rgb = Frames(t_f, rng.integers(0, 256, (6, h, w, 3), dtype=np.uint8))
    path = write_aedat(tmp_path / "rgb.aedat4", ev, rgb, w, h)
    with AedatReplay(path, Pacing(factor=0)) as src:
        _, _, fr3 = _drain(src)
    assert fr3 == rgb  # RGB in, RGB out (dv's BGR handled at the boundary)


def test_start_offset_and_loop(dvxplorer_path):
    pacing = Pacing(factor=0, loop=True, start_offset_us=300_000, batch_us=50_000)
    with AedatReplay(dvxplorer_path, pacing) as src:
        period = LAST_US + 1 - (FIRST_US + 300_000)
        got = []
        while (b := src.read()).loop < 3:
            assert b.time_shift_us == b.loop * period
            got.append(b.events)
    ev = Events.concat(got)  # raises if time ever went backwards across a batch
    assert ev.t_start >= FIRST_US + 300_000 and len(got[0]) > 0
    one_pass = sum(len(e) for e in got) / 3  # three whole passes
    with AedatReplay(dvxplorer_path, Pacing(factor=0, start_offset_us=300_000)) as src:
        assert sum(len(b.events) for b in src) == one_pass
    with pytest.raises(InvalidInputError, match="past the end"):
        AedatReplay(dvxplorer_path, Pacing(start_offset_us=10**9)).read()


class FakeClock:
    def __init__(self):
        self.now = 100.0
        self.sleeps = []

    def __call__(self):
        return self.now

    def sleep(self, s):
        self.sleeps.append(s)
        self.now += s


@pytest.mark.parametrize("factor", [1.0, 4.0])
def test_real_time_pacing_follows_the_wall_clock(dvxplorer_path, factor):
    clock = FakeClock()
    with AedatReplay(dvxplorer_path, Pacing(factor=factor), clock=clock, sleep=clock.sleep) as src:
        start = clock.now
        batches = list(src)
    span_s = (batches[-1].t_end_us - FIRST_US) / 1e6
    assert clock.now - start == pytest.approx(span_s / factor, rel=1e-6)
    assert src.pacer.lag_s(batches[-1].t_end_us) == 0


def test_pacer_does_not_sleep_at_factor_zero_and_validates():
    clock = FakeClock()
    p = Pacer(0, clock=clock, sleep=clock.sleep)
    p.wait_until(0)
    p.wait_until(10**9)
    assert clock.sleeps == []
    with pytest.raises(InvalidInputError, match="factor"):
        Pacing(factor=-1)
    with pytest.raises(InvalidInputError, match="batch_us"):
        Pacing(batch_us=0)


def test_bad_aedat_files_give_clear_errors(tmp_path, dvxplorer_path):
    data = dvxplorer_path.read_bytes()
    cases = {"truncated.aedat4": data[: len(data) // 2], "tiny.aedat4": data[:100],
             "foreign.aedat4": b"this is not an aedat4 file\n" * 10}
    corrupt = bytearray(data)
    corrupt[2000:2200] = bytes(b ^ 0xFF for b in corrupt[2000:2200])
    cases["corrupt.aedat4"] = bytes(corrupt)
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(ReplayFormatError) as err:
            list(AedatReplay(tmp_path / name, Pacing(factor=0), stall_s=2))
        assert name in str(err.value) and "Stacktrace" not in str(err.value)
    # dv-processing's LZ4 decoder spins on this damage; the child that decodes it is killed
    with pytest.raises(ReplayFormatError, match="stalled for 2 s"):
        list(AedatReplay(tmp_path / "corrupt.aedat4", Pacing(factor=0), stall_s=2))
    with pytest.raises(ReplayFormatError, match="no such file"):
        AedatReplay(tmp_path / "missing.aedat4")
    with pytest.raises(ReplayFormatError, match="no such file"):
        open_source(tmp_path / "x.txt")


def test_closing_a_replay_stops_its_stalled_decoder_from_another_thread(tmp_path, dvxplorer_path):
    corrupt = bytearray(dvxplorer_path.read_bytes())
    corrupt[300_000:300_200] = bytes(b ^ 0xFF for b in corrupt[300_000:300_200])  # a packet mid-file spins
    (tmp_path / "spin.aedat4").write_bytes(bytes(corrupt))
    replay = AedatReplay(tmp_path / "spin.aedat4", Pacing(factor=0), stall_s=600)
    errors = []

    def ingest():
        try:
            list(replay)
        except SensorError as exc:  # "closed", at whichever point the close caught the reader
            errors.append(str(exc))

    thread = threading.Thread(target=ingest)
    thread.start()
    replay.close()  # whatever the decoder is doing
    thread.join(60)
    assert not thread.is_alive() and len(errors) == 1 and "closed" in errors[0], errors


def test_a_replay_starts_at_the_first_frame_when_it_precedes_the_first_event(tmp_path):
    ev = make_events(2_000, 64, 48, t0=1_700_000_000_100_000, rate_hz=1e5)
    first_frame = ev.t_start - 30_000  # an APS frame stamped mid-exposure, before any event
    t_f = np.array([first_frame, ev.t_start + 5_000, ev.t_end - 10], np.int64)
    frames = Frames(t_f, np.random.default_rng(4).integers(0, 256, (3, 48, 64, 1), dtype=np.uint8))
    path = write_aedat(tmp_path / "f0.aedat4", ev, frames, 64, 48)
    with AedatReplay(path, Pacing(factor=0)) as src:
        assert src.info.t_range_us[0] == first_frame
        _, ev2, fr2 = _drain(src)
        assert src.stats.dropped == 0
    assert fr2 == frames and ev2 == ev  # nothing lost, the first frame included


def test_a_plain_script_without_a_main_guard_reads_an_aedat4(tmp_path, dvxplorer_path):
    """The decoder's child must not re-run the user's script (a spawn child imports ``__main__``)."""
    import subprocess
    import sys

    script = tmp_path / "count.py"
    script.write_text("from edmcgs.sensor.sources.aedat import AedatReplay\n"
                      "from edmcgs.sensor.sources.pacing import Pacing\n"
                      "print('script body ran')\n"
                      f"with AedatReplay({str(dvxplorer_path)!r}, Pacing(factor=0)) as src:\n"
                      "    print('events', sum(len(b.events) for b in src))\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.splitlines() == ["script body ran", f"events {DVX_EVENTS}"]
