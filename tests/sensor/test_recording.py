import subprocess
import sys

import h5py
import numpy as np
import pytest

from edmcgs.errors import InvalidInputError, RecordingError, ReplayFormatError
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import (
    FORMAT_VERSION,
    Recording,
    RecordingFile,
    RecordingWriter,
    read_recording,
    write_recording,
)
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.imu import IMU_DTYPE

from .conftest import make_events, make_recording


def _assert_same(a: Recording, b: Recording):
    assert (a.width, a.height, a.sensor, a.metadata) == (b.width, b.height, b.sensor, b.metadata)
    assert a.events == b.events and a.anchors == b.anchors and a.held_out == b.held_out
    for name in ("intrinsics", "trajectory_t_us", "trajectory_c2w"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y)
    assert a.contrast_threshold == b.contrast_threshold


def test_round_trip_everything(tmp_path):
    rec = make_recording()
    path = write_recording(tmp_path / "r.h5", rec)
    back = read_recording(path)
    _assert_same(rec, back)
    assert back.events.t.dtype == np.int64 and back.anchors.poses.dtype == np.float64
    assert back.t_range_us == (int(rec.events.t[0]), int(rec.events.t[-1]))
    assert [p.name for p in tmp_path.iterdir()] == ["r.h5"]  # no temporary left behind


def test_round_trip_minimal_and_grey(tmp_path):
    ev = make_events(100, 10, 8)
    rec = Recording(width=10, height=8, events=ev, anchors=Frames([ev.t[0]], np.zeros((1, 8, 10), np.uint8)))
    back = read_recording(write_recording(tmp_path / "m.h5", rec))
    _assert_same(rec, back)
    assert back.anchors.channels == 1 and back.held_out is None and back.intrinsics is None
    empty = Recording(width=10, height=8, events=Events.empty(), anchors=Frames.empty(8, 10))
    back = read_recording(write_recording(tmp_path / "e.h5", empty, compression="lzf"))
    assert len(back.events) == 0 and len(back.anchors) == 0 and back.t_range_us is None


def test_streaming_writer_matches_whole_write(tmp_path):
    rec = make_recording(n_events=50_000)
    with RecordingWriter(tmp_path / "s.h5", width=rec.width, height=rec.height, sensor=rec.sensor) as w:
        for i in range(0, len(rec.events), 7_000):
            w.append_events(rec.events[i:i + 7_000])
        for i in range(len(rec.anchors)):
            w.append_anchors(rec.anchors[i:i + 1])
        assert not (tmp_path / "s.h5").exists()  # nothing at the target until finished
        w.finish(held_out=rec.held_out, intrinsics=rec.intrinsics, trajectory_t_us=rec.trajectory_t_us,
                 trajectory_c2w=rec.trajectory_c2w, contrast_threshold=0.2, metadata=rec.metadata)
    _assert_same(rec, read_recording(tmp_path / "s.h5"))


def test_writer_rejects_bad_appends(tmp_path):
    with RecordingWriter(tmp_path / "b.h5", width=10, height=10) as w:
        w.append_events(Events([5, 6], [1, 2], [1, 2], [1, 1]))
        with pytest.raises(InvalidInputError, match="back in time"):
            w.append_events(Events([4], [1], [1], [1]))
        with pytest.raises(InvalidInputError, match="outside the 10x10"):
            w.append_events(Events([7], [10], [1], [1]))
        w.append_anchors(Frames([10], np.zeros((1, 10, 10, 3), np.uint8)))
        with pytest.raises(InvalidInputError, match="not after"):
            w.append_anchors(Frames([10], np.zeros((1, 10, 10, 3), np.uint8)))
        with pytest.raises(InvalidInputError, match="channels"):
            w.append_anchors(Frames([11], np.zeros((1, 10, 10, 1), np.uint8)))
        with pytest.raises(InvalidInputError, match="intrinsics"):
            w.finish(intrinsics=[np.nan, 1, 2, 3])
    assert len(read_recording(tmp_path / "b.h5").events) == 2


def test_exception_inside_the_block_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError), RecordingWriter(tmp_path / "x.h5", width=4, height=4) as w:
        w.append_events(Events([1], [1], [1], [1]))
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_killed_writer_leaves_no_file_that_looks_complete(tmp_path):
    code = f"""
import os, numpy as np
from edmcgs.sensor.files.recording import RecordingWriter
from edmcgs.sensor.events import Events
w = RecordingWriter({str(tmp_path / 'k.h5')!r}, width=8, height=8)
n = 300_000
w.append_events(Events(np.arange(n), np.zeros(n, int), np.zeros(n, int), np.ones(n, int)))
w._f.flush()
os._exit(3)
"""
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 3
    assert not (tmp_path / "k.h5").exists()
    leftovers = list(tmp_path.iterdir())
    assert len(leftovers) == 1 and leftovers[0].name.startswith(".k.tmp-")
    # either HDF5 refuses it (left open for writing) or it lacks the format mark written last
    with pytest.raises(ReplayFormatError, match=r"not a readable HDF5 file|not an edmcgs recording"):
        read_recording(leftovers[0])


def test_truncated_file(tmp_path):
    path = write_recording(tmp_path / "t.h5", make_recording(n_events=100_000))
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: len(data) // 2])
    with pytest.raises(ReplayFormatError, match="truncated or corrupt"):
        read_recording(tmp_path / "cut.h5")


def test_corrupted_event_chunk_is_detected(tmp_path):
    rec = make_recording(n_events=100_000)
    path = write_recording(tmp_path / "c.h5", rec)
    with h5py.File(path, "r") as f:
        offset = f["events/t"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    for i in range(offset + 4096, offset + 4160):
        raw[i] ^= 0x5A
    path.write_bytes(bytes(raw))
    with pytest.raises(ReplayFormatError, match="cannot read events"):
        read_recording(path)


def test_foreign_and_newer_files(tmp_path):
    foreign = tmp_path / "f.h5"
    with h5py.File(foreign, "w") as f:
        f["something/else"] = np.arange(3)
    with pytest.raises(ReplayFormatError, match=r"not an edmcgs recording.*something"):
        read_recording(foreign)
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(ReplayFormatError, match="not a readable HDF5 file"):
        read_recording(tmp_path / "text.h5")
    with pytest.raises(ReplayFormatError, match="no such file"):
        read_recording(tmp_path / "missing.h5")
    newer = write_recording(tmp_path / "n.h5", make_recording(n_events=10))
    with h5py.File(newer, "a") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(ReplayFormatError, match="newer edmcgs"):
        read_recording(newer)
    broken = write_recording(tmp_path / "b.h5", make_recording(n_events=10))
    with h5py.File(broken, "a") as f:
        del f["events/p"]
        f["events/p"] = np.zeros(3, np.float32)
    with pytest.raises(ReplayFormatError, match="events/p missing or not a 1-D int8"):
        RecordingFile(broken)


def test_recording_validation():
    ev = Events([1, 2], [5, 9], [0, 0], [1, -1])
    fr = Frames.empty(4, 10)
    with pytest.raises(InvalidInputError, match="outside the 9x4"):
        Recording(width=9, height=4, events=ev, anchors=Frames.empty(4, 9))
    with pytest.raises(InvalidInputError, match="anchors are 10x4 but the recording is 10x5"):
        Recording(width=10, height=5, events=ev, anchors=fr)
    with pytest.raises(InvalidInputError, match="JSON"):
        Recording(width=10, height=4, events=ev, anchors=fr, metadata={"x": float("nan")})
    with pytest.raises(InvalidInputError, match="contrast_threshold"):
        Recording(width=10, height=4, events=ev, anchors=fr, contrast_threshold=-1)
    with pytest.raises(InvalidInputError, match="given together"):
        Recording(width=10, height=4, events=ev, anchors=fr, trajectory_t_us=[1])
    with pytest.raises(InvalidInputError, match="strictly increasing"):
        Recording(width=10, height=4, events=ev, anchors=fr, trajectory_t_us=[2, 1],
                  trajectory_c2w=np.tile(np.eye(4), (2, 1, 1)))


def test_missing_folder_is_a_recording_error(tmp_path):
    with pytest.raises(RecordingError, match="does not exist"):
        write_recording(tmp_path / "no" / "r.h5", make_recording(n_events=10))


def test_recordings_get_the_usual_permissions(tmp_path):
    import os

    old = os.umask(0o027)
    try:
        path = write_recording(tmp_path / "r.h5", make_recording(n_events=100))
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o640


def _imu(n: int, t0: int = 0) -> np.ndarray:
    imu = np.zeros(n, IMU_DTYPE)
    imu["t"] = t0 + 1000 * np.arange(n)
    imu["accel"] = np.linspace(-1.0, 1.0, 3 * n).reshape(n, 3)
    imu["gyro"] = np.linspace(5.0, -5.0, 3 * n).reshape(n, 3)
    imu["temperature"] = 30.0
    return imu


def test_imu_and_novel_views_round_trip(tmp_path):
    rec = make_recording()
    held = rec.held_out
    novel = Frames(held.t_us, 255 - held.images, held.poses @ np.diag([1.0, 1.0, 1.0, 1.0]))
    rec = Recording(**{**rec.__dict__, "imu": _imu(50, int(rec.events.t[0])), "novel_views": novel})
    path = write_recording(tmp_path / "r.h5", rec)
    back = read_recording(path)
    _assert_same(rec, back)
    assert back.imu.dtype == IMU_DTYPE and np.array_equal(back.imu, rec.imu)
    assert back.novel_views == novel
    with RecordingFile(path) as f:
        assert np.array_equal(f.imu(), rec.imu) and f.frames("novel_views") == novel
    plain = read_recording(write_recording(tmp_path / "plain.h5", make_recording()))
    assert plain.imu is None and plain.novel_views is None  # a recording without them reads as before
    with h5py.File(path, "r") as f:  # the columns a reader without IMU_DTYPE finds
        assert f["imu/accel"].shape == (50, 3) and f["imu/t"].dtype == np.int64
        assert f.attrs["format_version"] == FORMAT_VERSION


def test_imu_and_novel_views_are_checked(tmp_path):
    rec = make_recording()
    held = rec.held_out
    with pytest.raises(InvalidInputError, match="IMU_DTYPE"):
        Recording(**{**rec.__dict__, "imu": np.zeros((4, 3))})
    with pytest.raises(InvalidInputError, match="non-decreasing"):
        Recording(**{**rec.__dict__, "imu": _imu(5)[::-1].copy()})
    bad = _imu(5)
    bad["gyro"][2, 1] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        Recording(**{**rec.__dict__, "imu": bad})
    with pytest.raises(InvalidInputError, match="poses"):
        Recording(**{**rec.__dict__, "novel_views": Frames(held.t_us, held.images)})
    path = write_recording(tmp_path / "r.h5", Recording(**{**rec.__dict__, "imu": _imu(8)}))
    with h5py.File(path, "a") as f:
        del f["imu/gyro"]
        f["imu"].create_dataset("gyro", data=np.zeros((7, 3), np.float32))
    with pytest.raises(ReplayFormatError, match="imu"):
        read_recording(path)


def test_points_round_trip_and_are_checked(tmp_path):
    rec = make_recording()
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 3))
    colors = rng.integers(0, 256, (40, 3), dtype=np.uint8)
    rec = Recording(**{**rec.__dict__, "points_xyz": xyz, "points_colors": colors})
    path = write_recording(tmp_path / "r.h5", rec)
    back = read_recording(path)
    _assert_same(rec, back)
    assert np.array_equal(back.points_xyz, xyz) and back.points_xyz.dtype == np.float64
    assert np.array_equal(back.points_colors, colors) and back.points_colors.dtype == np.uint8
    with h5py.File(path, "r") as f:
        assert f["points/xyz"].shape == (40, 3) and f.attrs["format_version"] == FORMAT_VERSION
    plain = read_recording(write_recording(tmp_path / "plain.h5", make_recording()))
    assert plain.points_xyz is None and plain.points_colors is None  # optional, as before
    with pytest.raises(InvalidInputError, match="together"):
        Recording(**{**rec.__dict__, "points_colors": None})
    with pytest.raises(InvalidInputError, match="finite"):
        Recording(**{**rec.__dict__, "points_xyz": np.full((40, 3), np.nan)})
    with pytest.raises(InvalidInputError, match="uint8"):
        Recording(**{**rec.__dict__, "points_colors": colors[:39]})
    with h5py.File(path, "r+") as f:  # a damaged group is a format error naming it
        del f["points/colors"]
        f["points"].create_dataset("colors", data=np.zeros((3, 3), np.uint8))
    with pytest.raises(ReplayFormatError, match="points"):
        read_recording(path)
