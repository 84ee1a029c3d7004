"""``edmcgs export``: the frame schedule and the GIF / MP4 writers (the end-to-end export against the
real server is in test_viewer_e2e.py)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, ImageSequence

from edmcgs.clients.export import GifWriter, Mp4Writer, gif_durations_ms, open_writer, sweep_times_us
from edmcgs.errors import InvalidInputError


def test_sweep_times_are_exact_microseconds_at_epoch_scale():
    t0 = 1_700_000_000_000_000
    times = sweep_times_us(t0, t0 + 1_000_000, fps=15)
    assert times.dtype == np.int64
    assert len(times) == 16 and times[0] == t0 and times[-1] == t0 + 1_000_000
    np.testing.assert_array_equal(np.diff(times), np.round(np.arange(1, 16) * 1e6 / 15).astype(np.int64)
                                  - np.round(np.arange(15) * 1e6 / 15).astype(np.int64))
    slow = sweep_times_us(t0, t0 + 1_000_000, fps=10, speed=0.5)  # slow motion: 20 frames per scene s
    assert len(slow) == 21 and slow[1] - slow[0] == 50_000
    assert list(sweep_times_us(t0, t0, fps=30)) == [t0]  # a single instant
    assert len(sweep_times_us(t0, t0 + 99_999, fps=10)) == 1  # t1 short of the next frame


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"fps": 0}, "fps"), ({"fps": float("nan")}, "fps"), ({"fps": 10, "speed": -1}, "speed"),
    ({"fps": 10, "speed": float("inf")}, "speed"),
])
def test_sweep_times_reject_bad_rates(kwargs, name):
    with pytest.raises(InvalidInputError, match=name):
        sweep_times_us(0, 1_000_000, **kwargs)


def test_sweep_times_reject_a_backwards_span():
    with pytest.raises(InvalidInputError, match="t1"):
        sweep_times_us(10, 5, fps=10)


@pytest.mark.parametrize("fps", [15, 24, 30, 7.5, 100])
def test_gif_delays_keep_the_rate_on_average(fps):
    durations = gif_durations_ms(300, fps)
    assert all(d % 10 == 0 and d >= 10 for d in durations)
    assert abs(sum(durations) - 300 * 1000 / fps) <= 5  # within half a GIF tick over 300 frames


def _frames(n, h=37, w=51, channels=3):
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, size=(h, w, channels), dtype=np.uint8)
    return [np.roll(base, 3 * k, axis=1) for k in range(n)]


@pytest.mark.parametrize("channels", [1, 3])
def test_gif_writer_round_trip(tmp_path, channels):
    path = tmp_path / "a.gif"
    writer = open_writer(path, fps=20)
    assert isinstance(writer, GifWriter)
    frames = _frames(5, channels=channels)
    for f in frames:
        writer.add(f)
    writer.close()
    with Image.open(path) as gif:
        assert gif.n_frames == 5 and gif.size == (51, 37)
        mode = "L" if channels == 1 else "RGB"
        got = [np.asarray(frame.convert(mode)) for frame in ImageSequence.Iterator(gif)]
        assert [frame.info["duration"] for frame in ImageSequence.Iterator(gif)] == [50] * 5
    if channels == 1:  # grey needs no palette reduction: lossless
        np.testing.assert_array_equal(np.stack(got), np.stack(frames)[..., 0])
    else:  # 256 colours per frame for random noise: close on average, and the frames differ
        assert np.abs(np.stack(got).astype(int) - np.stack(frames)).mean() < 20
        assert not np.array_equal(got[0], got[1])


def test_mp4_writer_round_trip_pads_odd_sizes(tmp_path):
    import imageio_ffmpeg  # the dev extra installs it
    path = tmp_path / "a.mp4"
    writer = open_writer(path, fps=10)
    assert isinstance(writer, Mp4Writer)
    # smooth frames (H.264 is lossy on noise): a moving gradient, odd height and width, grey
    y, x = np.mgrid[:37, :51]
    frames = [((x * 4 + y * 2 + 10 * k) % 256).astype(np.uint8)[..., None] for k in range(6)]
    for f in frames:
        writer.add(f)
    writer.close()
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    assert meta["size"] == (52, 38) and meta["fps"] == 10
    got = [np.frombuffer(b, np.uint8).reshape(38, 52, 3) for b in reader]
    assert len(got) == 6
    err = np.abs(got[3][:37, :51, 0].astype(int) - frames[3][..., 0]).mean()
    assert err < 12


def test_open_writer_refuses_other_suffixes(tmp_path):
    with pytest.raises(InvalidInputError, match=r"out must end in \.gif or \.mp4"):
        open_writer(tmp_path / "a.avi", fps=10)


def test_a_pose_starting_with_a_minus_sign_is_a_value_not_an_option():
    from edmcgs.clients.export import _joined_pose, _parser

    argv = _joined_pose(["out.gif", "--pose", "-0.15,0,0,1,0,0,0", "--fps", "5"])
    args = _parser().parse_args(argv)
    assert args.pose == "-0.15,0,0,1,0,0,0" and args.fps == 5


def test_export_refuses_to_overwrite_without_force(tmp_path, capsys):
    from edmcgs.clients.export import main

    out = tmp_path / "kept.gif"
    out.write_bytes(b"a user's file")
    with pytest.raises(SystemExit):
        main([str(out), "--url", "http://127.0.0.1:9"])
    assert "use --force" in capsys.readouterr().err and out.read_bytes() == b"a user's file"
