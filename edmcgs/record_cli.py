"""``edmcgs record``: ``edmcgs.sensor.record`` (copy a camera or replay to AEDAT4 / HDF5), plus,
for a file, the application layer's choices: ``--anchor-fps`` / ``--anchor-every`` store the anchor split
(the other frames held out), ``--intrinsics`` and ``--poses`` the camera, in the HDF5 written. With those,
``--start``, ``--duration`` and ``--no-frames`` cut the recording as a plain copy does; ``--factor``
(real-time pacing) is refused, the file being read whole."""

from __future__ import annotations

import sys

from edmcgs.errors import EdmcgsError
from edmcgs.filekind import HDF5_SUFFIXES, check_recording
from edmcgs.options import RecordingOptions, add_recording_arguments
from edmcgs.sensor import record
from edmcgs.sensor.files.recording import write_recording


def main(argv: list[str] | None = None) -> int:
    parser = record._parser()
    add_recording_arguments(parser, resolution=False)
    args = parser.parse_args(argv)
    options = RecordingOptions.from_args(args)
    if options == RecordingOptions(resolution=options.resolution):
        return record.main(argv)  # a plain copy, streamed
    if args.live or args.source is None:
        parser.error("--anchor-fps, --anchor-every, --intrinsics and --poses apply to a file, not --live")
    if args.output.suffix.lower() not in HDF5_SUFFIXES:
        parser.error("the anchor split, intrinsics and poses are stored in our HDF5 format: give -o OUT.h5")
    if args.output.exists() and not args.force:
        parser.error(f"{args.output} exists (use --force to replace it)")
    if args.factor:
        parser.error("--factor paces a plain copy; with --anchor-fps, --anchor-every, --intrinsics or "
                     "--poses the file is read whole, as fast as it decodes: leave out --factor")
    if args.no_frames and (args.anchor_fps is not None or args.anchor_every is not None):
        parser.error("--no-frames leaves no frames to choose anchors among: leave out --no-frames or "
                     "--anchor-fps / --anchor-every")
    from edmcgs.pipeline import open_recording

    try:
        check_recording(args.source)
        rec = open_recording(args.source, options, progress=not args.quiet, start_s=args.start,
                             duration_s=args.duration, frames=not args.no_frames)
        write_recording(args.output, rec)
    except EdmcgsError as exc:
        print(f"edmcgs record: error: {exc}", file=sys.stderr)
        return 1
    held = 0 if rec.held_out is None else len(rec.held_out)
    print(f"wrote {args.output}: {len(rec.events)} events, {len(rec.anchors)} anchors, "
          f"{held} held-out frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
