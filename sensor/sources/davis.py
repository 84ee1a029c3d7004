"""A live DAVIS camera (DAVIS346 and kin) over USB through dv-processing: events, APS frames, IMU.

Opening checks with pyusb that a DAVIS is attached before asking dv-processing for it, so the
errors say what is wrong: ``BackendMissing`` when pyusb finds no libusb (a system library),
``DeviceNotFound`` naming the USB ids looked for (dv-processing itself only raises a bare
IndexError). A camera unplugged mid-stream raises ``DeviceDisconnected`` from ``read()``; whoever
holds the ring buffer keeps what it has and may call ``reconnect()``, which retries with
exponential backoff.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import dv_processing as dv
import numpy as np
import usb.core

from edmcgs.errors import BackendMissing, DeviceDisconnected, DeviceNotFound, InvalidInputError, SensorError
from edmcgs.sensor.events import DEFAULT_MAX_DISORDER_US, Events
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import SensorBatch, SourceBase, StreamInfo
from edmcgs.sensor.sources.dv_bridge import dv_error_text, frame_image, imu_array, store_columns

INIVATION_VENDOR_ID = 0x152A
DAVIS_PRODUCT_IDS = {0x841A: "DAVIS FX3", 0x841B: "DAVIS FX2"}
LIBUSB_HINT = ("install the system library libusb-1.0 (Debian/Ubuntu: apt install libusb-1.0-0; "
               "Fedora: dnf install libusb1; macOS: brew install libusb)")


def _looked_for(serial: str | None) -> str:
    ids = ", ".join(f"0x{pid:04x} ({name})" for pid, name in DAVIS_PRODUCT_IDS.items())
    who = f" with serial number {serial!r}" if serial else ""
    return f"a DAVIS camera{who}: USB vendor 0x{INIVATION_VENDOR_ID:04x} (iniVation), product {ids}"


def find_davis_devices() -> list:
    """The pyusb devices that are DAVIS cameras. Raises BackendMissing without libusb."""
    try:
        found = list(usb.core.find(find_all=True, idVendor=INIVATION_VENDOR_ID) or [])
    except usb.core.NoBackendError as exc:
        raise BackendMissing(f"pyusb has no USB backend, so no camera can be found: {LIBUSB_HINT}") from exc
    return [d for d in found if d.idProduct in DAVIS_PRODUCT_IDS]


class DavisSource(SourceBase):
    """The first DAVIS on USB, or the one with ``serial``.

    ``read()`` waits up to ``read_timeout_s`` for data and returns a batch, empty if nothing came.
    """

    def __init__(self, serial: str | None = None, *, read_timeout_s: float = 0.05,
                 max_disorder_us: int = DEFAULT_MAX_DISORDER_US) -> None:
        super().__init__()
        if serial is not None and (not isinstance(serial, str) or not serial):
            raise InvalidInputError(f"serial must be a non-empty string, got {serial!r}")
        if not read_timeout_s > 0:
            raise InvalidInputError(f"read_timeout_s must be positive, got {read_timeout_s}")
        self.serial = serial
        self.read_timeout_s = float(read_timeout_s)
        self.max_disorder_us = max_disorder_us
        self.reconnects = 0
        self._cam = None
        self._last_t: int | None = None
        self._open()

    def _open(self) -> None:
        if not find_davis_devices():
            raise DeviceNotFound(f"no camera found: looked for {_looked_for(self.serial)}")
        try:
            cam = dv.io.camera.open(self.serial) if self.serial else dv.io.camera.open()
        except IndexError as exc:  # dv-processing's way of saying "no such camera"
            raise DeviceNotFound(f"dv-processing could not open {_looked_for(self.serial)} (is another "
                                 "program using it, or are the USB permissions/udev rules missing?)") from exc
        except RuntimeError as exc:
            raise DeviceNotFound(f"dv-processing could not open {_looked_for(self.serial)}: "
                                 f"{dv_error_text(exc)}") from exc
        if not cam.isEventStreamAvailable():
            raise SensorError(f"camera {cam.getCameraName()} has no event stream")
        width, height = cam.getEventResolution()
        has_frames = bool(cam.isFrameStreamAvailable())
        self._info = StreamInfo(
            width=int(width), height=int(height), sensor=cam.getCameraName(), has_frames=has_frames,
            has_imu=bool(cam.isImuStreamAvailable()), live=True,
            frame_size=tuple(int(v) for v in cam.getFrameResolution()) if has_frames else None)
        self._cam = cam

    @property
    def info(self) -> StreamInfo:
        return self._info

    def read(self) -> SensorBatch:
        """Events (and frames, IMU) received since the last read. Raises DeviceDisconnected if unplugged."""
        self._check_open()
        if self._cam is None:
            raise DeviceDisconnected(f"{self._info.sensor} is disconnected; call reconnect()")
        deadline = time.monotonic() + self.read_timeout_s
        while True:
            batch = self._poll()
            if batch is not None or time.monotonic() >= deadline:
                return batch if batch is not None else SensorBatch(events=Events.empty())
            time.sleep(0.001)

    def _poll(self) -> SensorBatch | None:
        cam = self._cam
        try:
            if not cam.isRunning():
                raise DeviceDisconnected(f"{self._info.sensor} stopped streaming (unplugged?)")
            stores = []
            while (store := cam.getNextEventBatch()) is not None:
                stores.append(store)
            frames = []
            if self._info.has_frames:
                while (frame := cam.getNextFrame()) is not None:
                    frames.append((int(frame.timestamp), frame_image(frame)))
            imu = []
            if self._info.has_imu:
                while (samples := cam.getNextImuBatch()) is not None and len(samples):
                    imu.append(imu_array(samples))
        except DeviceDisconnected:
            self._cam = None
            raise
        except (RuntimeError, IndexError) as exc:
            self._cam = None
            raise DeviceDisconnected(f"{self._info.sensor}: {dv_error_text(exc)}") from exc
        if not stores and not frames and not imu:
            return None
        cols = [store_columns(s) for s in stores]
        if cols:
            t, x, y, p = (np.concatenate([c[i] for c in cols]) for i in range(4))
        else:
            t = x = y = p = np.empty(0, np.int64)
        events, stats = Events.from_arrays(t, x, y, p, width=self._info.width, height=self._info.height,
                                           max_disorder_us=self.max_disorder_us, not_before_us=self._last_t)
        self._stats.add(stats)
        if len(events):
            self._last_t = events.t_end
        fr = None
        if frames:
            frames.sort(key=lambda item: item[0])
            fr = Frames([t for t, _ in frames], np.stack([img for _, img in frames]))
        return SensorBatch(events=events, frames=fr, imu=np.concatenate(imu) if imu else None)

    def reconnect(self, *, attempts: int = 10, initial_delay_s: float = 0.2, max_delay_s: float = 5.0,
                  sleep: Callable[[float], None] = time.sleep,
                  should_stop: Callable[[], bool] = lambda: False) -> None:
        """Reopen the camera, waiting initial_delay_s, 2x, 4x ... (capped at max_delay_s) between tries.

        Raises the last DeviceNotFound / BackendMissing after ``attempts`` failures.
        """
        self._check_open()
        self._cam = None
        delay, last = float(initial_delay_s), None
        for _ in range(max(1, attempts)):
            if should_stop():
                break
            sleep(delay)
            try:
                self._open()
            except (DeviceNotFound, BackendMissing) as exc:
                last = exc
                delay = min(max_delay_s, delay * 2)
                continue
            self.reconnects += 1
            return
        raise DeviceNotFound(f"could not reconnect after {attempts} attempts: {last}") from last

    def close(self) -> None:
        super().close()
        self._cam = None  # dv-processing releases the device with the handle
