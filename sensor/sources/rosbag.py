"""ROS 1 and ROS 2 bag replay, read by rosbags (``rosbags.highlevel.AnyReader``): the format of the Event
Camera Dataset, MVSEC and most event-based SLAM data.

What is taken, each from one topic (the first event topic in name order; for the others, the topic
nearest it in the topic tree, e.g. ``/davis/left/image_raw`` beside ``/davis/left/events``):

- events: ``dvs_msgs/EventArray`` or ``prophesee_event_msgs/EventArray`` (their definitions are built in,
  for ROS 2 bags that do not store them);
- frames: ``sensor_msgs/Image`` (mono8, mono16, rgb8, bgr8, rgba8, bgra8), at their header stamps;
- IMU: ``sensor_msgs/Imu``, converted to dv's units (g, degrees per second; no temperature: 0);
- the camera: the first ``sensor_msgs/CameraInfo`` (fx, fy, cx, cy and its distortion);
- ground truth: ``geometry_msgs/PoseStamped`` as the camera-to-world trajectory.

A ROS 2 bag is its folder (``metadata.yaml`` beside a ``.db3`` or ``.mcap``), or one of those files. Bags
are read forward message by message (never whole); opening one reads its index once for the time range.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from edmcgs.errors import EdmcgsError, InvalidInputError, ReplayFormatError, translated
from edmcgs.geometry import pose_from_quat
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.imu import IMU_DTYPE
from edmcgs.sensor.sources.base import Extras, StreamInfo
from edmcgs.sensor.sources.pacing import Pacing
from edmcgs.sensor.sources.replay import Ahead, Chunk, Replay

_EVENT_DEFS = """std_msgs/Header header
uint32 height
uint32 width
{pkg}/Event[] events
""", """uint16 x
uint16 y
builtin_interfaces/Time ts
bool polarity
"""
EVENT_TYPES = ("dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray")
IMAGE, IMU, CAMERA, POSE = ("sensor_msgs/msg/Image", "sensor_msgs/msg/Imu", "sensor_msgs/msg/CameraInfo",
                            "geometry_msgs/msg/PoseStamped")
_G = 9.80665  # m/s² per g
_ENCODINGS = {"mono8": (1, None), "rgb8": (3, None), "bgr8": (3, slice(None, None, -1)),
              "rgba8": (4, slice(0, 3)), "bgra8": (4, slice(2, None, -1))}


def typestore():
    """The latest ROS 2 message types plus the event arrays of the dvs and Prophesee drivers."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.LATEST)
    types = {}
    for msgtype in EVENT_TYPES:
        pkg = msgtype.split("/")[0]
        types.update(get_types_from_msg(_EVENT_DEFS[0].format(pkg=pkg), msgtype))
        types.update(get_types_from_msg(_EVENT_DEFS[1], f"{pkg}/msg/Event"))
    store.register(types)
    return store


def bag_path(path: Path) -> Path:
    """What rosbags opens: a ROS 1 bag file, or a ROS 2 bag's folder (also given by one of its files)."""
    if path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def _stamp_us(stamp) -> int:
    return int(stamp.sec) * 1_000_000 + int(stamp.nanosec) // 1000


def _nearest(topics: list[str], to: str) -> str | None:
    """The topic sharing the longest leading path with ``to`` (name order breaks ties)."""
    def shared(topic: str) -> int:
        a, b = topic.strip("/").split("/"), to.strip("/").split("/")
        return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))

    return max(sorted(topics), key=shared, default=None)


class RosbagReplay(Replay):
    """Replay a ROS 1 ``.bag`` or a ROS 2 bag (see the module docstring); ``resolution`` (width, height) for
    a bag whose event arrays and camera info state none."""

    def __init__(self, path: str | os.PathLike, pacing: Pacing | None = None, *,
                 resolution: tuple[int, int] | None = None, **kwargs) -> None:
        super().__init__(pacing, **kwargs)
        self.path = Path(path)
        if not self.path.exists():
            raise ReplayFormatError(f"{self.path}: no such file")
        self._store = self._read("load the message types", typestore)
        with self._read("open the bag", self._reader) as reader:
            by_type: dict[str, list[str]] = {}
            for c in reader.connections:
                by_type.setdefault(c.msgtype, []).append(c.topic)
            events = sorted(t for msgtype in EVENT_TYPES for t in by_type.get(msgtype, []))
            if not events:
                found = ", ".join(f"{t} [{m}]" for m, ts in sorted(by_type.items()) for t in ts)
                raise ReplayFormatError(f"{self.path}: no event topic ({' or '.join(EVENT_TYPES)}); "
                                        f"topics: {found or 'none'}")
            self._topics = {"events": events[0]} | {
                kind: _nearest(by_type.get(msgtype, []), events[0])
                for kind, msgtype in (("frames", IMAGE), ("imu", IMU), ("camera", CAMERA), ("poses", POSE))}
            first = self._first(reader, "events")
            width, height = int(first.width), int(first.height)
            camera = self._first(reader, "camera")
            frame = self._first(reader, "frames")
            if not width * height and camera is not None:
                width, height = int(camera.width), int(camera.height)
            if not width * height:
                if resolution is None:
                    raise ReplayFormatError(f"{self.path}: the event arrays state no resolution and there is "
                                            "no camera info; give the resolution (--resolution WIDTHxHEIGHT)")
                if len(resolution) != 2 or min(resolution) <= 0:
                    raise InvalidInputError(f"resolution must be (width, height) > 0, got {resolution!r}")
                width, height = (int(v) for v in resolution)
            times = [t for kind in ("events", "frames", "imu") for t in self._span(reader, kind)]
            self._extras = self._read("read the camera and the poses", lambda: self._camera_and_poses(
                reader, camera))
        self._info = StreamInfo(
            width=width, height=height, sensor=f"ROS bag {self._topics['events']}",
            has_frames=frame is not None, has_imu=self._topics["imu"] is not None, live=False,
            t_range_us=(min(times), max(times)) if times else None,
            frame_size=None if frame is None else (int(frame.width), int(frame.height)))

    def _read(self, what: str, fn):
        # rosbags' errors (ReaderError, deserialisation's) name what is wrong; ours pass through.
        def corrupt(exc: BaseException) -> ReplayFormatError:
            return ReplayFormatError(f"{self.path}: cannot {what} (not a ROS bag, truncated or corrupt?): "
                                     f"{exc}")

        with translated((Exception,), corrupt, keep=(EdmcgsError,)):
            return fn()

    def _reader(self):
        from rosbags.highlevel import AnyReader

        return self._read("open the bag",
                          lambda: AnyReader([bag_path(self.path)], default_typestore=self._store))

    def _raw(self, reader, kind: str) -> Iterator:
        """The topic's (connection, bag time, bytes) in bag order."""
        topic = self._topics[kind]
        if topic is None:
            return
        connections = [c for c in reader.connections if c.topic == topic]
        raw = self._read(f"read {topic}", lambda: iter(reader.messages(connections=connections)))
        while (item := self._read(f"read {topic}", lambda: next(raw, None))) is not None:
            yield item

    def _decode(self, reader, item):
        connection, _, data = item
        return self._read(f"decode {connection.topic}", lambda: reader.deserialize(data, connection.msgtype))

    def _messages(self, reader, kind: str) -> Iterator:
        return (self._decode(reader, item) for item in self._raw(reader, kind))

    def _first(self, reader, kind: str):
        return next(self._messages(reader, kind), None)

    def _span(self, reader, kind: str) -> list[int]:
        """First and last time of a topic (events: of their first and last message's events)."""
        first = last = None
        for item in self._raw(reader, kind):
            first, last = first or item, item
        if first is None:
            return []
        return _times(kind, self._decode(reader, first))[:1] + _times(kind, self._decode(reader, last))[-1:]

    def _camera_and_poses(self, reader, camera) -> Extras:
        intrinsics = distortion = None
        if camera is not None:
            k = [float(v) for v in camera.k]
            intrinsics = (k[0], k[4], k[2], k[5])
            distortion = tuple(float(v) for v in camera.d) if any(camera.d) else None
        t, c2w = [], []
        for msg in self._messages(reader, "poses"):
            p, q = msg.pose.position, msg.pose.orientation
            t.append(_stamp_us(msg.header.stamp))
            c2w.append(pose_from_quat([p.x, p.y, p.z], [q.w, q.x, q.y, q.z]))
        return Extras(intrinsics=intrinsics if intrinsics and intrinsics[0] > 0 else None,
                      distortion=distortion,
                      trajectory_t_us=np.array(t, np.int64) if t else None,
                      trajectory_c2w=np.stack(c2w) if c2w else None)

    def _chunks(self, begin_us: int) -> Iterator[Chunk]:
        readers = [self._reader() for _ in range(3)]  # one per stream, each read forward on its own
        with readers[0] as events_reader, readers[1] as frames_reader, readers[2] as imu_reader:
            frames = Ahead((_stamp_us(m.header.stamp), m) for m in self._messages(frames_reader, "frames"))
            imu = Ahead((_stamp_us(m.header.stamp), m) for m in self._messages(imu_reader, "imu"))
            for msg in self._messages(events_reader, "events"):
                if not len(msg.events):
                    continue
                t, x, y, p = _event_columns(msg)
                horizon = int(t[-1])  # more events at t[-1] may follow
                if horizon < begin_us:
                    continue
                yield self._chunk(self._validated(t, x, y, p), frames.until(horizon), imu.until(horizon),
                                  horizon)
            yield self._chunk(self._validated(*([np.empty(0, np.int64)] * 4)), frames.until(2**62),
                              imu.until(2**62), 2**62)

    def _chunk(self, events, frames: list, imu: list, horizon: int) -> Chunk:
        fr = None
        if frames:
            try:
                images = np.stack([_image(m) for _, m in frames])
            except ReplayFormatError as exc:
                raise ReplayFormatError(f"{self.path}: {exc}") from exc
            fr = self._read("decode the images", lambda: Frames([t for t, _ in frames], images))
        return Chunk(events=events, frames=fr, imu=_imu(imu) if imu else None, horizon_us=horizon)


def _times(kind: str, msg) -> list[int]:
    if kind == "events":
        return [_stamp_us(msg.events[0].ts), _stamp_us(msg.events[-1].ts)] if len(msg.events) else []
    return [_stamp_us(msg.header.stamp)]


def _event_columns(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    ev = msg.events
    t = np.fromiter((e.ts.sec * 1_000_000 + e.ts.nanosec // 1000 for e in ev), np.int64, len(ev))
    x = np.fromiter((e.x for e in ev), np.int64, len(ev))
    y = np.fromiter((e.y for e in ev), np.int64, len(ev))
    return t, x, y, np.fromiter((e.polarity for e in ev), np.bool_, len(ev))


def _image(msg) -> np.ndarray:
    """A sensor_msgs/Image as uint8 [H, W, C] (grey or RGB)."""
    h, w, encoding = int(msg.height), int(msg.width), str(msg.encoding).lower()
    data = np.asarray(msg.data, np.uint8)
    if encoding in ("mono16", "16uc1"):
        rows = data.reshape(h, int(msg.step))[:, :2 * w].copy().view(">u2" if msg.is_bigendian else "<u2")
        return (rows >> 8).astype(np.uint8)[..., None]
    if encoding not in _ENCODINGS:
        raise ReplayFormatError(f"image encoding {msg.encoding!r} is not read (mono8, mono16, rgb8, bgr8, "
                                "rgba8, bgra8 are)")
    channels, pick = _ENCODINGS[encoding]
    img = data.reshape(h, int(msg.step))[:, :w * channels].reshape(h, w, channels)
    return np.ascontiguousarray(img if pick is None else img[..., pick])


def _imu(items: list) -> np.ndarray:
    out = np.zeros(len(items), IMU_DTYPE)
    for i, (t, m) in enumerate(items):
        a, g = m.linear_acceleration, m.angular_velocity
        out[i] = (t, (a.x / _G, a.y / _G, a.z / _G), np.degrees([g.x, g.y, g.z]), 0.0)
    return out
