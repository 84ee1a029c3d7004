"""The live DAVIS path, up to the device: no camera is attached here, so only the pyusb presence
check and dv-processing's open call are replaced where a test needs a device; everything else is the
real code path (and the DVXplorer recording stands in for the camera's data stream)."""

import dv_processing as dv
import numpy as np
import pytest
import usb.core

from edmcgs.errors import BackendMissing, DeviceDisconnected, DeviceNotFound, SensorError
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ingest import Ingest
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.events import Events
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.davis import DavisSource
from edmcgs.sensor.sources.open import open_source
from tests.support.recordings import write_aedat

from .conftest import make_events


class FakeUsbDevice:
    def __init__(self, vendor, product):
        self.idVendor, self.idProduct = vendor, product


def _usb_finds(monkeypatch, devices):
    def find(find_all=False, idVendor=None, **kw):
        assert find_all and idVendor == 0x152A
        return iter([d for d in devices if d.idVendor == idVendor])

    monkeypatch.setattr(usb.core, "find", find)


def test_this_machine_without_a_camera_gets_a_clear_error():
    with pytest.raises(SensorError) as err:  # unpatched: libusb missing, or present with no camera
        DavisSource()
    assert isinstance(err.value, BackendMissing | DeviceNotFound)
    assert "libusb-1.0" in str(err.value) or "0x152a" in str(err.value)


def test_no_libusb_backend_names_the_system_library(monkeypatch):
    def find(**kw):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", find)
    with pytest.raises(BackendMissing, match=r"libusb-1\.0.*apt install libusb-1\.0-0"):
        DavisSource()


def test_no_device_says_what_was_looked_for(monkeypatch):
    _usb_finds(monkeypatch, [FakeUsbDevice(0x152A, 0x8419)])  # an iniVation device that is not a DAVIS
    with pytest.raises(DeviceNotFound, match=r"vendor 0x152a.*0x841a \(DAVIS FX3\).*0x841b \(DAVIS FX2\)"):
        DavisSource()
    with pytest.raises(DeviceNotFound, match="serial number 'DAVIS346_00000499'"):
        open_source(live=True, serial="DAVIS346_00000499")


def test_dv_processing_index_error_is_translated(monkeypatch):
    _usb_finds(monkeypatch, [FakeUsbDevice(0x152A, 0x841A)])  # pyusb sees one; the real dv open finds none
    with pytest.raises(DeviceNotFound, match="dv-processing could not open a DAVIS camera") as err:
        DavisSource()
    assert isinstance(err.value.__cause__, IndexError)


class UnpluggableCamera:
    """A camera stand-in: a real AEDAT4 recording read through the same dv API as a live camera,
    which stops running (as an unplugged camera does) after ``reads`` polls."""

    def __init__(self, path, reads):
        self._rec = dv.io.MonoCameraRecording(str(path))
        self._reads = reads

    def isRunning(self):
        self._reads -= 1
        return self._reads >= 0

    def __getattr__(self, name):
        return getattr(self._rec, name)


@pytest.fixture
def camera_file(tmp_path):
    w, h = 346, 260
    ev = make_events(20_000, w, h, rate_hz=1e5)
    t_f = np.linspace(ev.t_start, ev.t_end, 4).astype(np.int64)
    frames = Frames(t_f, np.random.default_rng(0).integers(0, 256, (4, h, w, 1), dtype=np.uint8))
    return write_aedat(tmp_path / "cam.aedat4", ev, frames, w, h, camera="DAVIS346_00000499"), ev, frames


@pytest.fixture
def later_file(tmp_path, camera_file):
    """What the camera streams after being plugged back in: later events."""
    _, ev, _ = camera_file
    later = make_events(5_000, 346, 260, t0=ev.t_end + 1_000_000, rate_hz=1e5, seed=9)
    return write_aedat(tmp_path / "later.aedat4", later, None, 346, 260, camera="DAVIS346_00000499"), later


def test_unplugged_mid_stream_keeps_the_ring_and_reconnects(monkeypatch, camera_file, later_file):
    path, ev, frames = camera_file
    later_path, later = later_file
    _usb_finds(monkeypatch, [FakeUsbDevice(0x152A, 0x841A)])
    opens = {"n": 0}

    def open_camera(*args):
        opens["n"] += 1
        if opens["n"] in (2, 3):  # replugging: the first two tries find nothing yet
            raise IndexError("vector::_M_range_check")
        return UnpluggableCamera(path, reads=1) if opens["n"] == 1 else UnpluggableCamera(later_path, 10**6)

    monkeypatch.setattr(dv.io.camera, "open", open_camera)
    src = DavisSource()
    assert src.info.live and src.info.sensor == "DAVIS346_00000499" and src.info.has_frames
    first = src.read()  # the whole file arrives in one poll
    assert first.events == ev and first.frames == frames
    ring, anchors = EventRingBuffer(100_000), AnchorStore()
    ring.push(first.events)
    anchors.add_frames(first.frames)
    with pytest.raises(DeviceDisconnected, match="stopped streaming"):
        src.read()
    assert len(ring) == len(ev)  # what was buffered is kept
    sleeps = []
    src.reconnect(initial_delay_s=0.1, sleep=sleeps.append)
    assert sleeps == [0.1, 0.2, 0.4] and src.reconnects == 1 and opens["n"] == 4
    again = src.read()
    assert again.events == later and again.frames is None
    ring.push(again.events)
    assert ring.stats().pushed == len(ev) + len(later) and src.stats.dropped == 0


def test_ingest_thread_reconnects_and_gives_up_cleanly(monkeypatch, camera_file):
    path, ev, _ = camera_file
    _usb_finds(monkeypatch, [FakeUsbDevice(0x152A, 0x841B)])
    opens = {"n": 0}

    def open_camera(*args):
        opens["n"] += 1
        if opens["n"] > 1:
            raise IndexError("gone")
        return UnpluggableCamera(path, reads=1)

    monkeypatch.setattr(dv.io.camera, "open", open_camera)
    src = DavisSource()
    # the default backoff sleeps for seconds: shorten it for the test
    monkeypatch.setattr(src, "reconnect", lambda **kw: DavisSource.reconnect(
        src, attempts=3, initial_delay_s=0.001, **kw))
    ring, anchors = EventRingBuffer(50_000), AnchorStore()
    ingest = Ingest(src, ring, anchors).start()
    ingest._thread.join(timeout=30)
    assert not ingest.running and ingest.disconnects == 1
    assert isinstance(ingest.error, DeviceNotFound) and "after 3 attempts" in str(ingest.error)
    assert ring.stats().pushed == len(ev) and len(anchors) == 4  # kept across the failed reconnect
    assert ring.slice(ev.t_start, ev.t_end) == ev.time_slice(ev.t_start, ev.t_end)


def test_ingest_replay_to_the_end(camera_file):
    path, ev, frames = camera_file
    ring, anchors = EventRingBuffer(len(ev)), AnchorStore()
    from edmcgs.sensor.sources.pacing import Pacing

    ingest = Ingest(open_source(path, pacing=Pacing(factor=0)), ring, anchors)
    ingest.run()
    assert ingest.finished and ingest.error is None
    assert ring.watermark_us == ev.t_end + 1 and len(anchors) == len(frames)
    assert ring.slice(ev.t_start, ev.t_end + 1) == ev
    assert anchors.tau(int(frames.t_us[2]) + 5) == frames.t_us[2]
    assert isinstance(Events.empty(), Events)
