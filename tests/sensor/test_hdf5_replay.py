import tracemalloc

import h5py
import numpy as np
import pytest

from edmcgs.errors import InvalidInputError, ReplayFormatError
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.hdf5 import Hdf5Replay
from edmcgs.sensor.sources.open import open_source
from edmcgs.sensor.sources.pacing import Pacing

from .conftest import make_events, make_recording


def _drain(src):
    batches = list(src)
    frames = [b.frames for b in batches if b.frames is not None]
    return batches, Events.concat([b.events for b in batches]), (Frames.concat(frames) if frames else None)


def test_our_recording_replays_exactly_in_small_chunks(tmp_path):
    rec = make_recording(n_events=40_000, n_anchors=5)
    path = write_recording(tmp_path / "r.h5", rec)
    with Hdf5Replay(path, Pacing(factor=0, batch_us=3_000), chunk_events=4_999) as src:
        assert src.layout == "edmcgs recording"
        assert (src.info.width, src.info.height, src.info.sensor) == (64, 48, "simulated")
        assert src.info.has_frames and src.info.t_range_us == rec.t_range_us
        batches, ev, fr = _drain(src)
        assert src.stats.dropped == 0
    assert ev == rec.events
    assert np.array_equal(fr.t_us, rec.anchors.t_us) and np.array_equal(fr.images, rec.anchors.images)
    for b in batches:  # each frame arrives in the batch whose window holds its timestamp
        if b.frames is not None:
            assert (b.frames.t_us < b.t_end_us).all() and (b.frames.t_us >= b.t_end_us - 3_000).all()


def test_frames_carry_the_poses_the_recording_states_when_it_states_them_all_along(tmp_path):
    """A replay's frames are posed by the recording's trajectory (a checkpoint's online anchors past its
    span then know where the camera is); a trajectory that does not cover the recording poses none."""
    from dataclasses import replace

    rec = make_recording(n_events=20_000, n_anchors=5)
    for name, stated, posed in (("all.h5", rec, True),
                                ("late.h5", replace(rec, trajectory_t_us=rec.trajectory_t_us[1:],
                                                    trajectory_c2w=rec.trajectory_c2w[1:]), False)):
        with Hdf5Replay(write_recording(tmp_path / name, stated), Pacing(factor=0, batch_us=3_000)) as src:
            _, _, fr = _drain(src)
        assert np.array_equal(fr.t_us, rec.anchors.t_us)
        if posed:
            np.testing.assert_allclose(fr.poses, rec.trajectory_c2w, rtol=0, atol=1e-12)
        else:
            assert fr.poses is None


def test_start_offset_seeks_by_binary_search(tmp_path):
    rec = make_recording(n_events=40_000)
    path = write_recording(tmp_path / "r.h5", rec)
    t0 = rec.t_range_us[0]
    with open_source(path, pacing=Pacing(factor=0, start_offset_us=12_345)) as src:
        _, ev, _ = _drain(src)
    assert ev == rec.events.time_slice(t0 + 12_345, 2**62)


def _write_dsec(path, ev, t_offset, *, ms_to_idx=True):
    with h5py.File(path, "w") as f:
        f["events/x"] = ev.x
        f["events/y"] = ev.y
        f["events/p"] = (ev.p > 0).astype(np.uint8)
        f["events/t"] = (ev.t - t_offset).astype(np.uint32)
        f["t_offset"] = np.int64(t_offset)
        if ms_to_idx:
            ms = np.arange(0, (ev.t_end - t_offset) // 1000 + 1) * 1000
            f["ms_to_idx"] = np.searchsorted(ev.t - t_offset, ms).astype(np.uint64)


def test_dsec_layout(tmp_path):
    ev = make_events(50_000, 640, 480, t0=1_600_000_000_000_000, rate_hz=2e6)
    _write_dsec(tmp_path / "events.h5", ev, t_offset=1_600_000_000_000_000 - 5_000)
    with Hdf5Replay(tmp_path / "events.h5", Pacing(factor=0), chunk_events=8_000) as src:
        assert src.layout == "DSEC" and (src.info.width, src.info.height) == (640, 480)
        _, got, fr = _drain(src)
    assert got == ev and fr is None
    with Hdf5Replay(tmp_path / "events.h5", Pacing(factor=0), resolution=(320, 480)) as src:
        _, got, _ = _drain(src)
        assert src.stats.out_of_bounds == int(np.sum(ev.x >= 320)) > 0  # dropped and counted
    assert got == ev[ev.x < 320]


def _write_v2e(path, ev, frames=None):
    rows = np.stack([ev.t, ev.x, ev.y, (ev.p > 0)], axis=1).astype(np.uint32)
    with h5py.File(path, "w") as f:
        f.create_dataset("events", data=rows, maxshape=(None, 4), compression="gzip")
        if frames is not None:
            f["frame"] = frames.images[..., 0]
            f["frame_ts"] = frames.t_us.astype(np.uint32)
            f["frame_idx"] = np.searchsorted(ev.t, frames.t_us).astype(np.uint64)


def test_v2e_layout_with_and_without_frames(tmp_path):
    ev = make_events(30_000, 120, 90, t0=0, rate_hz=1e6)  # v2e time starts at 0 µs
    with Hdf5Replay(_write_v2e(tmp_path / "a.h5", ev) or tmp_path / "a.h5", Pacing(factor=0)) as src:
        assert src.layout == "v2e"
        assert (src.info.width, src.info.height) == (int(ev.x.max()) + 1, int(ev.y.max()) + 1)  # scanned
        _, got, _ = _drain(src)
    assert got == ev
    frames = Frames(np.array([100, 20_000], np.int64), np.zeros((2, 96, 128, 1), np.uint8) + 7)
    _write_v2e(tmp_path / "b.h5", ev, frames)
    with Hdf5Replay(tmp_path / "b.h5", Pacing(factor=0)) as src:
        assert (src.info.width, src.info.height) == (128, 96) and src.info.has_frames
        _, got, fr = _drain(src)
    assert got == ev and fr == frames


def test_v2e_small_disorder_is_sorted_and_counted(tmp_path):
    t = np.array([0, 10, 20, 15, 30, 40], np.uint32)  # 15 is 5 µs behind: sorted into place
    rows = np.stack([t, np.arange(6), np.zeros(6), np.ones(6)], axis=1).astype(np.uint32)
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f["events"] = rows
    with Hdf5Replay(tmp_path / "d.h5", Pacing(factor=0), resolution=(8, 8)) as src:
        _, got, _ = _drain(src)
        assert src.stats.reordered == 1 and src.stats.dropped == 0
    assert got.t.tolist() == [0, 10, 15, 20, 30, 40] and got.x.tolist() == [0, 1, 3, 2, 4, 5]


def test_unknown_layout_lists_keys_and_supported_layouts(tmp_path):
    with h5py.File(tmp_path / "u.h5", "w") as f:
        f["events/xs"] = np.zeros(3)
        f["events/ts"] = np.zeros(3)
    with pytest.raises(ReplayFormatError) as err:
        Hdf5Replay(tmp_path / "u.h5")
    msg = str(err.value)
    assert "events/xs" in msg and "events/ts" in msg and "DSEC" in msg and "v2e" in msg and "edmcgs" in msg
    with pytest.raises(InvalidInputError, match="resolution"):
        Hdf5Replay(tmp_path / "u.h5", resolution=(0, 3))


def test_truncated_and_corrupt_files(tmp_path):
    path = write_recording(tmp_path / "r.h5", make_recording(n_events=200_000))
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises(ReplayFormatError, match="truncated or corrupt"):
        list(Hdf5Replay(tmp_path / "cut.h5", Pacing(factor=0)))
    with h5py.File(path, "r") as f:
        offset = f["events/x"].id.get_chunk_info(0).byte_offset
    raw = bytearray(data)
    raw[offset + 100:offset + 164] = bytes(b ^ 0x33 for b in raw[offset + 100:offset + 164])
    (tmp_path / "bad.h5").write_bytes(bytes(raw))
    with pytest.raises(ReplayFormatError, match=r"cannot read events \[0, "):
        list(Hdf5Replay(tmp_path / "bad.h5", Pacing(factor=0)))


def test_replay_memory_is_bounded_by_the_chunk(tmp_path):
    n = 3_000_000
    ev = make_events(n, 346, 260, rate_hz=5e6)
    _write_dsec(tmp_path / "big.h5", ev, t_offset=int(ev.t_start), ms_to_idx=False)
    del ev
    tracemalloc.start()
    try:
        with Hdf5Replay(tmp_path / "big.h5", Pacing(factor=0, batch_us=5_000), chunk_events=1 << 16) as src:
            total = sum(len(b.events) for b in src)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert total == n
    # a few chunks (and 5 ms windows of 25k events) in flight, never the whole 39 MB of events
    assert peak < 0.1 * n * 13, peak
