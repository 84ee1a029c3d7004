"""``edmcgs export``: a time sweep of a running edmcgs service, written as a GIF or an MP4.

    edmcgs export sweep.gif                                   # the whole renderable span, 15 fps
    edmcgs export sweep.mp4 --t0 0.5 --t1 2 --fps 30 --speed 0.25 --url http://host:8000 --token T

Each frame is one ``GET /render`` through the Python client, at scene times t0, t0 + speed/fps, ...
up to t1: every frame is rendered (a websocket sweep would drop frames when the encoder falls
behind). A few renders are kept in flight so that the server's render workers stay busy. GIF goes
through Pillow; MP4 (H.264) through the ffmpeg binary of ``imageio-ffmpeg`` (``pip install
'edmcgs[video]'``). The output appears whole or not at all (a temporary file, renamed at the end).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
from PIL import Image
from tqdm import tqdm

from edmcgs import protocol
from edmcgs.atomic import atomic_output
from edmcgs.clients.client import Client, ServiceError
from edmcgs.errors import EdmcgsError, InvalidInputError

FORMATS = (".gif", ".mp4")


def sweep_times_us(t0_us: int, t1_us: int, fps: float, speed: float = 1.0) -> np.ndarray:
    """Scene times of the frames: t0, t0 + speed/fps s, ... <= t1. int64 [N], N >= 1.

    Integer microseconds from a float64 step: exact for any span a recording has (< 2^53 µs).
    """
    if not (math.isfinite(fps) and fps > 0):
        raise InvalidInputError(f"fps must be a finite number > 0, got {fps!r}")
    if not (math.isfinite(speed) and speed > 0):
        raise InvalidInputError(f"speed must be a finite number > 0, got {speed!r}")
    if t1_us < t0_us:
        raise InvalidInputError(f"t1 must not be before t0 (t0_us={t0_us}, t1_us={t1_us})")
    step_us = 1e6 * speed / fps
    count = math.floor((t1_us - t0_us) / step_us + 1e-9) + 1
    return t0_us + np.round(np.arange(count, dtype=np.float64) * step_us).astype(np.int64)


def gif_durations_ms(count: int, fps: float) -> list[int]:
    """Per-frame GIF delays: GIF counts in 10 ms steps, so round the frames' end times, not each delay,
    and the animation keeps the requested rate on average (15 fps: 70, 60, 70, 70, 60, 70 ... ms)."""
    ends = [round((k + 1) * 100 / fps) * 10 for k in range(count)]
    return [max(10, end - start) for start, end in zip([0, *ends[:-1]], ends, strict=True)]


class GifWriter:
    """Frames kept as palette images (a GIF is written in one go at the end)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps, self.frames = path, fps, []

    def add(self, pixels: np.ndarray) -> None:
        """pixels: uint8 [H, W, C], C = 1 or 3."""
        image = Image.fromarray(pixels[..., 0] if pixels.shape[2] == 1 else pixels)
        self.frames.append(image if image.mode == "L" else image.quantize(256))

    def close(self) -> None:
        first, *rest = self.frames
        first.save(self.path, format="GIF", save_all=True, append_images=rest, loop=0,
                   duration=gif_durations_ms(len(self.frames), self.fps), disposal=1)


class Mp4Writer:
    """H.264 in yuv420p (what every player reads), frames piped to ffmpeg as they come."""

    def __init__(self, path: Path, fps: float):
        try:
            import imageio_ffmpeg
        except ImportError:
            raise EdmcgsError("MP4 export needs the ffmpeg binary of imageio-ffmpeg: "
                              "pip install 'edmcgs[video]' (or write a .gif)") from None
        self._ffmpeg = imageio_ffmpeg
        self.path, self.fps, self._pipe, self._size = path, fps, None, None

    def add(self, pixels: np.ndarray) -> None:
        """pixels: uint8 [H, W, C], C = 1 or 3."""
        if pixels.shape[2] == 1:
            pixels = np.repeat(pixels, 3, axis=2)
        # yuv420p needs even sides: repeat the last row / column rather than rescale the image.
        h, w = pixels.shape[:2]
        pixels = np.pad(pixels, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        if self._pipe is None:
            self._size = (pixels.shape[1], pixels.shape[0])
            self._pipe = self._ffmpeg.write_frames(
                str(self.path), self._size, fps=self.fps, codec="libx264", pix_fmt_out="yuv420p",
                quality=7, macro_block_size=1, ffmpeg_log_level="error", output_params=["-f", "mp4"])
            self._pipe.send(None)
        if (pixels.shape[1], pixels.shape[0]) != self._size:
            raise EdmcgsError(f"frame size changed mid-export: {self._size} then {pixels.shape[1::-1]}")
        self._pipe.send(np.ascontiguousarray(pixels).tobytes())

    def close(self) -> None:
        if self._pipe is not None:
            self._pipe.close()


def open_writer(path: Path, fps: float) -> GifWriter | Mp4Writer:
    """The writer for ``path``'s suffix (.gif or .mp4)."""
    suffix = path.suffix.lower()
    if suffix == ".gif":
        return GifWriter(path, fps)
    if suffix == ".mp4":
        return Mp4Writer(path, fps)
    raise InvalidInputError(f"out must end in {' or '.join(FORMATS)}, got {str(path)!r}")


def default_span_us(scene: dict) -> tuple[int, int]:
    """The span a sweep covers unless told otherwise: what the server can render now."""
    renderable = scene.get("renderable") or {}
    t0 = renderable.get("t_us_min", scene["t_start_us"])
    t1 = renderable.get("t_us_max", scene["t_end_us"])
    return int(t0), int(t1)


def export_sweep(client: Client, out: str | os.PathLike, *, t0: float | None = None, t1: float | None = None,
                 fps: float = 15.0, speed: float = 1.0, pose=None, width: int | None = None,
                 height: int | None = None, jobs: int = 2, max_frames: int = 3000,
                 progress: bool = True) -> int:
    """Render scene times t0..t1 (seconds from the scene's start; None: the renderable span's ends)
    every ``speed / fps`` s from ``pose`` (None: the event camera's own) and write them to ``out``
    (.gif or .mp4) at ``fps``. Returns the number of frames written.

    Raises InvalidInputError for bad arguments, the client's ServiceError subclasses for what the
    server refuses (a time outside what it can render: TimeUnavailable, with the valid range).
    """
    out = Path(out)
    if out.suffix.lower() not in FORMATS:
        raise InvalidInputError(f"out must end in {' or '.join(FORMATS)}, got {str(out)!r}")
    if not out.parent.is_dir():
        raise InvalidInputError(f"out: folder {str(out.parent)!r} does not exist")
    if jobs < 1:
        raise InvalidInputError(f"jobs must be >= 1, got {jobs}")
    scene = client.scene()
    span0, span1 = default_span_us(scene)
    start = int(scene["t_start_us"])
    t0_us = span0 if t0 is None else protocol.t_us_of_seconds(float(t0), start)
    t1_us = span1 if t1 is None else protocol.t_us_of_seconds(float(t1), start)
    times = sweep_times_us(t0_us, t1_us, fps, speed)
    if len(times) > max_frames:
        raise InvalidInputError(f"the sweep has {len(times)} frames, more than max_frames={max_frames}: "
                                f"lower fps, shorten t0..t1, raise speed or raise max_frames")
    if pose is not None:
        pose = protocol.check_pose_numbers(np.asarray(pose, dtype=np.float64).reshape(-1).tolist())

    def render(t_us: int) -> np.ndarray:
        pixels, _meta = client.render(t_us=int(t_us), pose=pose, width=width, height=height,
                                      format="msgpack")
        return pixels

    with atomic_output(out, InvalidInputError) as tmp:
        writer = open_writer(tmp, fps)
        with ThreadPoolExecutor(jobs) as pool, tqdm(total=len(times), unit="frame", disable=not progress,
                                                     desc=out.name) as bar:
            in_flight: deque = deque()
            for t_us in times:
                in_flight.append(pool.submit(render, t_us))
                if len(in_flight) >= jobs:
                    writer.add(in_flight.popleft().result())
                    bar.update()
            while in_flight:
                writer.add(in_flight.popleft().result())
                bar.update()
        writer.close()
    return len(times)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="edmcgs export", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="output file, .gif or .mp4")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="the service (default: %(default)s)")
    p.add_argument("--token", default=os.environ.get("EDMCGS_TOKEN"),
                   help="bearer token (default: $EDMCGS_TOKEN)")
    p.add_argument("--t0", type=float,
                   help="start, seconds from the scene's start (default: the first renderable time)")
    p.add_argument("--t1", type=float,
                   help="end, seconds from the scene's start (default: the last renderable time)")
    p.add_argument("--fps", type=float, default=15.0, help="frames per second of the output (default: 15)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="scene seconds per output second; < 1 is slow motion (default: 1)")
    p.add_argument("--pose", help="camera-to-world (OpenCV axes): 16 numbers row-major or 7 "
                                  "(tx,ty,tz,qw,qx,qy,qz: the quaternion's w FIRST, where TUM files put it "
                                  "last), comma-separated (default: the event camera's own pose)")
    p.add_argument("--width", type=int, help="frame width (default: the event camera's)")
    p.add_argument("--height", type=int, help="frame height (default: the event camera's)")
    p.add_argument("--jobs", type=int, default=2, help="renders in flight (default: 2)")
    p.add_argument("--max-frames", type=int, default=3000, help="refuse longer sweeps (default: 3000)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    return p


def _joined_pose(argv: list[str]) -> list[str]:
    """``--pose -0.15,0,...`` as ``--pose=-0.15,0,...``: argparse takes a value starting with a minus
    sign for an option unless it is a single number."""
    out, args = [], iter(argv)
    for arg in args:
        if arg == "--pose" and (value := next(args, None)) is not None:
            out.append(f"--pose={value}")
        else:
            out.append(arg)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(_joined_pose(sys.argv[1:] if argv is None else argv))
    if args.out.exists() and not args.force:
        parser.error(f"{args.out} exists (use --force to replace it)")
    try:
        pose = None if args.pose is None else protocol.parse_pose_text(args.pose)
        with Client(args.url, args.token) as client:
            n = export_sweep(client, args.out, t0=args.t0, t1=args.t1, fps=args.fps, speed=args.speed,
                             pose=pose, width=args.width, height=args.height, jobs=args.jobs,
                             max_frames=args.max_frames, progress=not args.quiet)
    except (EdmcgsError, ServiceError, protocol.ProtocolError, OSError) as exc:
        print(f"edmcgs export: error: {exc}", file=sys.stderr)
        return 1
    except httpx.HTTPError as exc:  # connection refused, timeout ...
        print(f"edmcgs export: error: cannot reach {args.url}: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {n} frames to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
