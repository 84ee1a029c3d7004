"""``edmcgs record``: record a live camera or any replay to AEDAT4 (dv-processing's writer) or our HDF5.

    edmcgs record SOURCE.aedat4|SOURCE.h5 -o OUT.h5 [--duration S] [--start S] [--factor F]
    edmcgs record --live [--serial SN] -o OUT.aedat4 --duration 10

Output files are written atomically: nothing appears at OUT until the recording is complete. Ctrl-C
stops a recording early and keeps what was recorded (the usual way to end a live capture).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from tqdm import tqdm

from edmcgs.atomic import atomic_output, ensure_room
from edmcgs.errors import DiskFullError, EdmcgsError, InvalidInputError, RecordingError
from edmcgs.filekind import AEDAT_SUFFIXES, HDF5_SUFFIXES, check_recording
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording, RecordingWriter
from edmcgs.sensor.frames import Frames
from edmcgs.sensor.sources.base import EventSource, Extras, SensorBatch, StreamInfo
from edmcgs.sensor.sources.open import open_source, parse_resolution
from edmcgs.sensor.sources.pacing import Pacing


class AedatOutput:
    """Batches -> an AEDAT4 file through dv-processing's MonoCameraWriter, atomically (events, frames and
    IMU: a source's calibration and ground-truth trajectory have no place in it; our HDF5 keeps them)."""

    def __init__(self, path: Path, info: StreamInfo, *, frames: bool = True) -> None:
        # Imported here: reading recordings (read_source, which training uses) needs no dv-processing.
        import dv_processing as dv

        from edmcgs.sensor.sources import dv_bridge

        self._path, self._bridge = path, dv_bridge
        self._atomic = atomic_output(path, RecordingError)
        tmp = self._atomic.__enter__()
        config = dv.io.MonoCameraWriter.Config(info.sensor)
        config.addEventStream((info.width, info.height))
        self._frames = frames and info.has_frames
        if self._frames:
            config.addFrameStream(info.frame_size)
        if info.has_imu:
            config.addImuStream()
        try:
            ensure_room(path, 0)
            self._writer = dv.io.MonoCameraWriter(str(tmp), config)
        except DiskFullError as exc:
            self.abort(exc)
            raise
        except RuntimeError as exc:
            self.abort(exc)
            raise RecordingError(f"cannot write {path}: {dv_bridge.dv_error_text(exc)}") from exc
        self._imu = info.has_imu

    def write(self, batch: SensorBatch) -> None:
        ensure_room(self._path, 16 * len(batch.events)
                    + (0 if batch.frames is None else batch.frames.images.nbytes))
        bridge = self._bridge
        if len(batch.events):
            self._writer.writeEvents(bridge.event_store(batch.events))
        if self._frames and batch.frames is not None:
            for i in range(len(batch.frames)):
                self._writer.writeFrame(bridge.image_frame(int(batch.frames.t_us[i]), batch.frames.images[i]))
        if self._imu and batch.imu is not None:
            for sample in bridge.imu_samples(batch.imu):
                self._writer.writeImu(sample)

    def finish(self, metadata: dict, extras: Extras) -> None:
        self._writer = None  # dv flushes and closes the file when the writer is released
        self._atomic.__exit__(None, None, None)

    def abort(self, exc: BaseException) -> None:
        self._writer = None
        self._atomic.__exit__(type(exc), exc, exc.__traceback__)


class Hdf5Output:
    """Batches -> our HDF5 recording (events, anchor frames, and the source's intrinsics and ground-truth
    trajectory), atomically."""

    def __init__(self, path: Path, info: StreamInfo, *, frames: bool = True) -> None:
        self._frames = frames and info.has_frames
        if self._frames and info.frame_size != (info.width, info.height):
            raise RecordingError(f"the source's frames are {info.frame_size} but its events "
                                 f"{(info.width, info.height)}; our recordings need one resolution "
                                 "(use --no-frames to record events only)")
        self._writer = RecordingWriter(path, width=info.width, height=info.height, sensor=info.sensor)

    def write(self, batch: SensorBatch) -> None:
        self._writer.append_events(batch.events)
        if self._frames and batch.frames is not None:
            self._writer.append_anchors(batch.frames)

    def finish(self, metadata: dict, extras: Extras) -> None:
        self._writer.finish(metadata=metadata, intrinsics=extras.intrinsics,
                            trajectory_t_us=extras.trajectory_t_us, trajectory_c2w=extras.trajectory_c2w)

    def abort(self, exc: BaseException) -> None:
        self._writer.abort(exc)


class MemoryOutput:
    """Batches -> a ``Recording`` in memory (``read_source``): events, and frames as anchors."""

    def __init__(self, info: StreamInfo, *, frames: bool = True) -> None:
        if frames and info.has_frames and info.frame_size != (info.width, info.height):
            raise RecordingError(f"the source's frames are {info.frame_size} but its events "
                                 f"{(info.width, info.height)}; a recording needs one resolution")
        self._info, self._frames = info, frames and info.has_frames
        self._events: list[Events] = []
        self._anchors: list[Frames] = []
        self.recording: Recording | None = None

    def write(self, batch: SensorBatch) -> None:
        self._events.append(batch.events)
        if self._frames and batch.frames is not None:
            self._anchors.append(batch.frames)

    def finish(self, metadata: dict, extras: Extras) -> None:
        info = self._info
        anchors = Frames.concat(self._anchors) if self._anchors else Frames.empty(info.height, info.width)
        self.recording = Recording(width=info.width, height=info.height, events=Events.concat(self._events),
                                   anchors=anchors, sensor=info.sensor, metadata=metadata,
                                   intrinsics=extras.intrinsics, trajectory_t_us=extras.trajectory_t_us,
                                   trajectory_c2w=extras.trajectory_c2w)

    def abort(self, exc: BaseException) -> None:
        self._events, self._anchors = [], []


def read_source(source: EventSource, *, progress: bool = False, source_name: str = "") -> Recording:
    """A whole replay in memory (never paced: read as fast as it decodes); what the source dropped
    is in ``metadata["source_stats"]``."""
    out = MemoryOutput(source.info)
    record(source, out, progress=progress, source_name=source_name)
    return out.recording


def _output(path: Path | MemoryOutput, info: StreamInfo, frames: bool):
    if isinstance(path, MemoryOutput):
        return path
    suffix = path.suffix.lower()
    if suffix in AEDAT_SUFFIXES:
        return AedatOutput(path, info, frames=frames)
    if suffix in HDF5_SUFFIXES:
        return Hdf5Output(path, info, frames=frames)
    raise InvalidInputError(
        f"output {path}: expected a name ending in {', '.join(AEDAT_SUFFIXES + HDF5_SUFFIXES)}")


def record(source: EventSource, output: Path | MemoryOutput, *, duration_s: float | None = None,
           frames: bool = True, progress: bool = True, source_name: str = "") -> dict:
    """Copy ``source`` to ``output`` until its end, ``duration_s`` of stream time (counted from the first
    event), or Ctrl-C.

    Returns a summary (events, frames, stream seconds, whether interrupted, the source's drop counts).
    """
    info = source.info
    out = _output(output, info, frames)
    t_begin = t_stop = None
    n_events = n_frames = 0
    interrupted = False
    total = duration_s if duration_s is not None else (
        (info.t_range_us[1] - info.t_range_us[0]) / 1e6 if info.t_range_us else None)
    bar = tqdm(total=total, unit="s", desc=f"reading {source_name or 'the source'}"
               if isinstance(output, MemoryOutput) else f"recording {output.name}", disable=not progress,
               bar_format="{l_bar}{bar}| {n:.2f}/{total_fmt} s [{elapsed}<{remaining}{postfix}]")
    shown = 0.0
    try:
        while True:
            try:
                batch = source.read()
            except KeyboardInterrupt:
                interrupted = True
                break
            if batch is None:
                break
            ev = batch.events
            if t_begin is None and len(ev):  # durations count from the first event
                t_begin = ev.t_start
                t_stop = None if duration_s is None else t_begin + round(duration_s * 1e6)
            done = False
            if t_stop is not None:
                reached = batch.t_end_us if batch.t_end_us is not None else (ev.t_end if len(ev) else None)
                if reached is not None and reached >= t_stop:
                    done = True
                    ev = ev.time_slice(-(2**62), t_stop)
                    fr = batch.frames.time_slice(-(2**62), t_stop) if batch.frames is not None else None
                    imu = batch.imu[batch.imu["t"] < t_stop] if batch.imu is not None else None
                    batch = SensorBatch(events=ev, frames=fr if fr is not None and len(fr) else None,
                                        imu=imu, t_end_us=t_stop)
            out.write(batch)
            n_events += len(batch.events)
            n_frames += 0 if batch.frames is None else len(batch.frames)
            now = batch.t_end_us if batch.t_end_us is not None else batch.events.t_end
            if t_begin is not None and now is not None:
                elapsed = (now - t_begin) / 1e6
                bar.update(max(0.0, min(elapsed, total or math.inf) - shown))
                shown = max(shown, min(elapsed, total or math.inf))
                bar.set_postfix(events=n_events, refresh=False)
            if done:
                break
        summary = {"events": n_events, "frames": n_frames, "seconds": shown, "interrupted": interrupted,
                   "source": source_name, "sensor": info.sensor, "source_stats": source.stats.as_dict()}
        extras = source.extras
        if extras.distortion is not None:
            summary["lens_distortion"] = list(extras.distortion)
        out.finish({"recorded_by": "edmcgs record", **summary}, extras)
        return summary
    except BaseException as exc:
        out.abort(exc)
        raise
    finally:
        bar.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="edmcgs record", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", nargs="?", help="recording to replay (.aedat4, .h5, .hdf5)")
    p.add_argument("-o", "--output", required=True, type=Path, help="output file (.aedat4, .h5, .hdf5)")
    p.add_argument("--live", action="store_true", help="record the DAVIS camera on USB instead of a file")
    p.add_argument("--serial", help="with --live: the camera's serial number (default: the first one)")
    p.add_argument("--duration", type=float,
                   help="seconds of stream time to record, from the first event (default: all, or Ctrl-C)")
    p.add_argument("--start", type=float, default=0.0, help="replays: skip this many seconds first")
    p.add_argument("--factor", type=float, default=0.0,
                   help="replays: real-time factor (1 = wall clock; default 0 = as fast as possible)")
    p.add_argument("--resolution", help="HDF5 layouts without one (DSEC, v2e): WIDTHxHEIGHT, e.g. 640x480")
    p.add_argument("--no-frames", action="store_true", help="record events only")
    p.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.live == (args.source is not None):
        parser.error("give a SOURCE file to replay, or --live (not both)")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        parser.error(f"--duration must be a positive number of seconds, got {args.duration}")
    if not (math.isfinite(args.start) and args.start >= 0):
        parser.error(f"--start must be >= 0 seconds, got {args.start}")
    if args.output.exists() and not args.force:
        parser.error(f"{args.output} exists (use --force to replace it)")
    try:
        if args.source is not None:
            check_recording(args.source)
        pacing = Pacing(factor=args.factor, start_offset_us=round(args.start * 1e6))
        source = open_source(args.source, live=args.live, serial=args.serial, pacing=pacing,
                             resolution=parse_resolution(args.resolution))
        with source:
            summary = record(source, args.output, duration_s=args.duration, frames=not args.no_frames,
                             progress=not args.quiet, source_name=args.source or "live")
    except EdmcgsError as exc:
        print(f"edmcgs record: error: {exc}", file=sys.stderr)
        return 1
    dropped = summary["source_stats"]["dropped"]
    print(f"wrote {args.output}: {summary['events']} events, {summary['frames']} frames, "
          f"{summary['seconds']:.3f} s" + (" (stopped by Ctrl-C)" if summary["interrupted"] else "")
          + (f"; {dropped} invalid events dropped: {summary['source_stats']}" if dropped else ""))
    return 0
