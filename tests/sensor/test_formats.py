"""Every camera's files: Prophesee RAW / DAT (real recordings from faery's test data, tests/data/prophesee),
a real DVS128's jAER AEDAT 2.0 (tests/data/jaer), ROS 1 and ROS 2 bags (written here with rosbags' own
writers), the RPG text layout and jAER / cAER AEDAT (written here by their published layouts): each
replays, records to our HDF5, and trains when it has frames."""

import struct

import numpy as np
import pytest

from edmcgs.errors import ReplayFormatError, TrainingError
from edmcgs.pipeline import open_recording, training_data
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import read_recording
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.record import main as record_main
from edmcgs.sensor.sources.open import detect_format, open_source
from edmcgs.sensor.sources.pacing import Pacing
from tests.support.recordings import DATA

PROPHESEE = DATA / "prophesee"
JAER = DATA / "jaer"
T0 = 1_500_000_000_000_000  # µs


def _drain(src):
    batches = list(src)
    frames = [b.frames for b in batches if b.frames is not None]
    imu = [b.imu for b in batches if b.imu is not None]
    return (Events.concat([b.events for b in batches]), Frames.concat(frames) if frames else None,
            np.concatenate(imu) if imu else None)


# --------------------------------------------------------------------------- Prophesee, real files

@pytest.mark.parametrize(("name", "size", "count", "first", "last", "sensor"), [
    ("evt2.raw", (640, 480), 198_341, 913_716_224, 913_742_763, "hal_plugin_gen3_fx3"),  # Gen3, EVT 2.0
    ("evt3.raw", (1280, 720), 132_290, 11_200_224, 11_510_896, "hal_plugin_imx636_evk4"),  # EVK4, EVT 3.0
    ("gen4.dat", (1280, 720), 100_000, 5_856, 203_100, "DAT"),  # EVK4, DAT 2
])
def test_prophesee_files_replay_as_faery_reads_them(name, size, count, first, last, sensor):
    import faery

    path = PROPHESEE / name
    assert detect_format(path) == "prophesee"
    with open_source(path, pacing=Pacing(factor=0)) as src:
        assert (src.info.width, src.info.height) == size and sensor in src.info.sensor
        assert src.info.t_range_us == (first, last) and not src.info.has_frames
        ev, frames, _ = _drain(src)
        assert src.stats.dropped == 0
    assert (len(ev), ev.t_start, ev.t_end, frames) == (count, first, last, None)
    theirs = np.concatenate(list(faery.events_stream_from_file(path, dimensions_fallback=size)))
    np.testing.assert_array_equal(ev.t, theirs["t"])
    np.testing.assert_array_equal(ev.x, theirs["x"])
    np.testing.assert_array_equal(ev.y, theirs["y"])
    np.testing.assert_array_equal(ev.p, np.where(theirs["on"], 1, -1))


def test_a_prophesee_file_records_to_our_hdf5_and_is_refused_for_training_with_the_reason(tmp_path):
    out = tmp_path / "evk4.h5"
    copy = tmp_path / "no_suffix"  # told apart by content, not by name
    copy.write_bytes((PROPHESEE / "evt3.raw").read_bytes())
    assert record_main([str(copy), "-o", str(out), "--duration", "0.1", "--quiet"]) == 0
    rec = read_recording(out)
    with open_source(PROPHESEE / "evt3.raw", pacing=Pacing(factor=0)) as src:
        whole, _, _ = _drain(src)
    assert rec.events == whole.time_slice(whole.t_start, whole.t_start + 100_000)
    assert (rec.width, rec.height) == (1280, 720) and "imx636" in rec.sensor
    with pytest.raises(TrainingError, match="no anchor frames"):
        training_data(open_recording(out))
    with pytest.raises(TrainingError, match="no anchor frames"):
        training_data(open_recording(PROPHESEE / "gen4.dat"))


def test_a_raw_file_without_a_size_asks_for_one(tmp_path):
    header_end = (PROPHESEE / "evt2.raw").read_bytes().index(b"% evt 2.0\n") + len(b"% evt 2.0\n")
    data = (PROPHESEE / "evt2.raw").read_bytes()
    bare = tmp_path / "bare.raw"
    bare.write_bytes(b"% evt 2.0\n" + data[header_end:])
    with pytest.raises(ReplayFormatError, match=r"bare.raw: its header states no sensor size.*--resolution"):
        open_source(bare)
    with open_source(bare, pacing=Pacing(factor=0), resolution=(640, 480)) as src:
        assert len(_drain(src)[0]) == 198_341
    (tmp_path / "cut.raw").write_bytes(data[:300])
    assert len(_drain(open_source(tmp_path / "cut.raw", pacing=Pacing(factor=0)))[0]) < 100
    (tmp_path / "junk.bin").write_bytes(b"\x00\x01junk")
    with pytest.raises(ReplayFormatError, match=r"junk.bin is not a recording read here.*ROS 1 bag"):
        open_source(tmp_path / "junk.bin")


# --------------------------------------------------------------------------- ROS bags

def _bag(path, ros2: bool):
    """A DAVIS-like bag written with rosbags' own writer: events, frames, IMU, camera info, poses."""
    from edmcgs.sensor.sources.rosbag import typestore

    store = typestore()
    T = store.types

    def stamp(us):
        return T["builtin_interfaces/msg/Time"](sec=us // 1_000_000, nanosec=us % 1_000_000 * 1000)

    def header(us):
        return T["std_msgs/msg/Header"](stamp=stamp(us), frame_id="davis")

    if ros2:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=9), store.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1
    Vector3, Quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    rng = np.random.default_rng(5)
    events = []
    with writer:
        def topic(name, msgtype):
            connection = writer.add_connection(name, msgtype, typestore=store)
            return lambda us, msg: writer.write(connection, us * 1000, serialize(msg, msgtype))

        ev_out, img_out = topic("/davis/events", "dvs_msgs/msg/EventArray"), topic("/davis/image_raw",
                                                                                    "sensor_msgs/msg/Image")
        imu_out, cam_out = topic("/davis/imu", "sensor_msgs/msg/Imu"), topic("/davis/camera_info",
                                                                            "sensor_msgs/msg/CameraInfo")
        pose_out = topic("/optitrack/davis", "geometry_msgs/msg/PoseStamped")
        topic("/other/events", "dvs_msgs/msg/EventArray")  # a second camera, later in name order: unused
        cam_out(T0, T["sensor_msgs/msg/CameraInfo"](
            header=header(T0), height=12, width=16, distortion_model="plumb_bob", d=np.zeros(5),
            k=np.array([20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1]), r=np.eye(3).ravel(), p=np.zeros(12),
            binning_x=0, binning_y=0, roi=T["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
        for k in range(4):
            t = T0 + 10_000 * k + np.sort(rng.integers(0, 10_000, 50))
            x, y, p = rng.integers(0, 16, 50), rng.integers(0, 12, 50), rng.integers(0, 2, 50)
            events.append((t, x, y, p))
            arrays = [T["dvs_msgs/msg/Event"](x=int(a), y=int(b), ts=stamp(int(c)), polarity=bool(d))
                      for c, a, b, d in zip(t, x, y, p, strict=True)]
            ev_out(int(t[0]), T["dvs_msgs/msg/EventArray"](header=header(int(t[0])), height=12, width=16,
                                                           events=arrays))
            img = (np.arange(12 * 16, dtype=np.uint8) * (k + 1)).reshape(12, 16)
            img_out(T0 + 10_000 * k + 5_000, T["sensor_msgs/msg/Image"](
                header=header(T0 + 10_000 * k + 5_000), height=12, width=16, encoding="mono8", is_bigendian=0,
                step=16, data=img.ravel()))
            imu_out(T0 + 10_000 * k + 1_000, T["sensor_msgs/msg/Imu"](
                header=header(T0 + 10_000 * k + 1_000), orientation=Quaternion(x=0, y=0, z=0, w=1),
                orientation_covariance=np.zeros(9), angular_velocity=Vector3(x=np.pi, y=0, z=0),
                angular_velocity_covariance=np.zeros(9), linear_acceleration=Vector3(x=0, y=0, z=9.80665),
                linear_acceleration_covariance=np.zeros(9)))
            pose_out(T0 + 10_000 * k, T["geometry_msgs/msg/PoseStamped"](
                header=header(T0 + 10_000 * k), pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=0.1 * k, y=0, z=0),
                    orientation=Quaternion(x=0, y=0, z=0, w=1))))
    return [np.concatenate(c) for c in zip(*events, strict=True)]


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_a_bag_replays_records_and_trains(tmp_path, ros2):
    path = tmp_path / ("davis" if ros2 else "davis.bag")
    t, x, y, p = _bag(path, ros2)
    assert detect_format(path) == "rosbag"
    with open_source(path, pacing=Pacing(factor=0)) as src:
        info = src.info
        assert (info.width, info.height, info.frame_size) == (16, 12, (16, 12)) and info.has_imu
        assert info.sensor == "ROS bag /davis/events"
        assert info.t_range_us == (int(t[0]), max(int(t[-1]), T0 + 35_000))
        ev, frames, imu = _drain(src)
        extras = src.extras
    assert ev == Events(t, x, y, np.where(p > 0, 1, -1))
    assert frames.t_us.tolist() == [T0 + 10_000 * k + 5_000 for k in range(4)]
    assert frames.images.shape == (4, 12, 16, 1)
    assert frames.images[2, 1, 3, 0] == (16 + 3) * 3 % 256
    assert imu["t"].tolist() == [T0 + 10_000 * k + 1_000 for k in range(4)]
    np.testing.assert_allclose(imu["accel"][0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(imu["gyro"][0], [180, 0, 0], atol=1e-4)
    assert extras.intrinsics == (20.0, 21.0, 7.5, 5.5) and extras.distortion is None
    assert extras.trajectory_t_us.tolist() == [T0 + 10_000 * k for k in range(4)]
    np.testing.assert_allclose(extras.trajectory_c2w[3, :3, 3], [0.3, 0, 0])
    out = tmp_path / "bag.h5"
    assert record_main([str(path), "-o", str(out), "--quiet"]) == 0
    rec = read_recording(out)
    assert rec.events == ev and rec.anchors == frames and rec.intrinsics.tolist() == [20, 21, 7.5, 5.5]
    assert rec.trajectory_t_us.tolist() == extras.trajectory_t_us.tolist()
    data = training_data(open_recording(path))
    assert len(data.anchors_t_us) == 4 and data.intrinsics.fx == 20.0
    np.testing.assert_allclose(data.anchor_poses[2][:3, 3], [0.25, 0, 0])  # on the ground-truth trajectory


def test_a_bag_without_events_says_what_it_holds(tmp_path):
    from rosbags.rosbag1 import Writer

    from edmcgs.sensor.sources.rosbag import typestore

    with Writer(tmp_path / "imu.bag") as writer:
        writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=typestore())
    with pytest.raises(ReplayFormatError, match=r"imu.bag: no event topic .*topics: /imu \[sensor_msgs/msg/"):
        open_source(tmp_path / "imu.bag")


# --------------------------------------------------------------------------- the RPG text layout

def _rpg(folder):
    from PIL import Image

    (folder / "images").mkdir(parents=True)
    rng = np.random.default_rng(2)
    n = 300
    t = np.sort(rng.integers(0, 40_000, n)) + 1_000
    x, y, p = rng.integers(0, 24, n), rng.integers(0, 18, n), rng.integers(0, 2, n)
    rows = zip(t, x, y, p, strict=True)
    (folder / "events.txt").write_text("".join(f"{a / 1e6:.9f} {b} {c} {d}\n" for a, b, c, d in rows))
    lines = []
    for k in range(4):
        Image.fromarray(np.full((18, 24), 40 * k, np.uint8)).save(folder / "images" / f"frame_{k:08d}.png")
        lines.append(f"{(k * 10_000 + 2_000) / 1e6:.9f} images/frame_{k:08d}.png\n")
    (folder / "images.txt").write_text("".join(lines))
    (folder / "imu.txt").write_text("".join(f"{(k * 5_000 + 500) / 1e6:.9f} 0 0 9.80665 0 0 0\n"
                                            for k in range(8)))
    (folder / "groundtruth.txt").write_text("".join(f"{k * 0.01:.6f} {k} 0 0 0 0 0 1\n" for k in range(5)))
    (folder / "calib.txt").write_text("30.0 31.0 11.5 8.5 -0.3 0.1 0 0 0\n")
    return t, x, y, p


def test_the_rpg_layout_replays_records_and_trains(tmp_path, capsys):
    folder = tmp_path / "shapes"
    t, x, y, p = _rpg(folder)
    for given in (folder, folder / "events.txt"):
        assert detect_format(given) == "rpg"
    with open_source(folder, pacing=Pacing(factor=0)) as src:
        assert (src.info.width, src.info.height, src.info.frame_size) == (24, 18, (24, 18))
        ev, frames, imu = _drain(src)
        extras = src.extras
    assert ev == Events(t, x, y, np.where(p > 0, 1, -1))
    assert frames.t_us.tolist() == [2_000, 12_000, 22_000, 32_000] and frames.images[3].max() == 120
    assert len(imu) == 8 and imu["accel"][0].tolist() == pytest.approx([0, 0, 1])
    assert extras.intrinsics == (30.0, 31.0, 11.5, 8.5) and extras.distortion == (-0.3, 0.1, 0.0, 0.0, 0.0)
    assert extras.trajectory_t_us.tolist() == [0, 10_000, 20_000, 30_000, 40_000]
    out = tmp_path / "shapes.h5"
    assert record_main([str(folder), "-o", str(out), "--quiet"]) == 0
    rec = read_recording(out)
    assert rec.events == ev and rec.anchors == frames and rec.metadata["lens_distortion"][0] == -0.3
    data = training_data(open_recording(out))
    assert len(data.anchors_t_us) == 4
    capsys.readouterr()
    open_recording(folder)
    assert "states a lens distortion" in capsys.readouterr().err
    (folder / "events.txt").write_text("0.1 1 2 1\n0.2 x 3 0\n")
    with pytest.raises(ReplayFormatError, match=r"events.txt: the lines after byte 0 are not 't x y p'"):
        open_source(folder)


# --------------------------------------------------------------------------- jAER AEDAT 2.0 / cAER 3.1

def test_a_real_dvs128_aedat2_file_replays_every_event_and_records(tmp_path):
    # tests/data/jaer: a DVS128's jAER recording with no AEChip line (its file name names the chip). The
    # figures are an independent decode's of jAER's layout (PyAedatTools' reading agrees): 10,615 DVS
    # events, 6,986 of them raw polarity 1 (OFF in jAER), raw x and y summing to 722,101 and 682,733;
    # one event 179 µs behind its predecessor, reordered.
    path = JAER / "DVS128-2014-10-21T17-41-53+0200-20000-0.aedat"
    with open_source(path, pacing=Pacing(factor=0)) as src:
        assert (src.info.width, src.info.height) == (128, 128) and "DVS128" in src.info.sensor
        assert src.info.t_range_us == (171_754_426, 177_119_891)
        ev, _, _ = _drain(src)
        assert src.stats.dropped == 0 and src.stats.reordered == 1
    n = 10_615
    assert (len(ev), ev.t_start, ev.t_end) == (n, 171_754_426, 177_119_891)
    assert int((ev.p < 0).sum()) == 6_986
    # jAER mirrors the DVS128's x; its origin is the lower left, ours the upper left
    assert int(ev.x.astype(np.int64).sum()) == 127 * n - 722_101
    assert int(ev.y.astype(np.int64).sum()) == 127 * n - 682_733
    out = tmp_path / "dvs128.h5"
    assert record_main([str(path), "-o", str(out), "--quiet"]) == 0
    assert read_recording(out).events == ev
    with pytest.raises(TrainingError, match="no anchor frames"):
        training_data(open_recording(out))


def test_jaer_aedat2_davis_and_caer_aedat31_replay_and_record(tmp_path):
    # AEDAT 2.0 from a DAVIS240C: address then timestamp, big-endian; one APS sample and one special
    # event among the DVS ones; the clock wraps once.
    words = [(0 << 22 | 5 << 12 | 1 << 11, 100), (1 << 31 | 7, 150), (3 << 22 | 9 << 12, 200),
             (1 << 10, 250), (179 << 22 | 239 << 12 | 1 << 11, 300), (4 << 22 | 1 << 12, 2**32 - 10),
             (10 << 22 | 20 << 12, 5)]
    header = b"#!AER-DAT2.0\r\n# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"
    aedat2 = tmp_path / "davis240c.aedat"
    aedat2.write_bytes(header + b"".join(struct.pack(">II", a, ts) for a, ts in words))
    with open_source(aedat2, pacing=Pacing(factor=0)) as src:
        assert (src.info.width, src.info.height) == (240, 180) and "DAVIS240C" in src.info.sensor
        ev, _, _ = _drain(src)
    assert ev.t.tolist() == [100, 200, 300, 2**32 - 10, 2**32 + 5]
    assert ev.x.tolist() == [5, 9, 239, 1, 20] and ev.y.tolist() == [179, 176, 0, 175, 169]
    assert ev.p.tolist() == [1, -1, 1, -1, -1]
    # AEDAT 3.1 from cAER: a polarity packet (one invalid event), an IMU packet skipped
    head = b"#!AER-DAT3.1\r\n#Format: RAW\r\n#Source 1: DVS128\r\n#!END-HEADER\r\n"

    def packet(kind, size, rows, overflow=0):
        n = len(rows)
        return struct.pack("<hhiiiiii", kind, 1, size, 4, overflow, n, n, n) + b"".join(rows)

    polarity = [struct.pack("<Ii", 3 << 17 | 4 << 2 | 1 << 1 | 1, 10), struct.pack("<Ii", 1 << 17 | 0, 20),
                struct.pack("<Ii", 127 << 17 | 127 << 2 | 1, 30)]
    aedat3 = tmp_path / "gesture.aedat"
    imu = packet(3, 36, [bytes(36)])
    aedat3.write_bytes(head + packet(1, 8, polarity) + imu + packet(1, 8, polarity[2:], 1))
    out = tmp_path / "gesture.h5"
    assert record_main([str(aedat3), "-o", str(out), "--quiet"]) == 0
    rec = read_recording(out)
    assert (rec.width, rec.height) == (128, 128) and "DVS128" in rec.sensor
    assert rec.events.t.tolist() == [10, 30, 2**31 + 30] and rec.events.x.tolist() == [3, 127, 127]
    assert rec.events.y.tolist() == [4, 127, 127] and rec.events.p.tolist() == [1, -1, -1]
    aedat3.write_bytes(head + packet(1, 8, polarity)[:40])
    with pytest.raises(ReplayFormatError, match=r"gesture.aedat: a packet cut short"):
        open_source(aedat3)
