"""``edmcgs poses RECORDING -o TRAJ.txt``: the camera's poses from the recording's own frames, by structure
from motion (``edmcgs.poses``), written as a TUM trajectory that ``--poses TRAJ.txt`` reads back (an
application edge: the recording is read through ``edmcgs.pipeline``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from edmcgs.errors import EdmcgsError
from edmcgs.options import RecordingOptions, add_recording_arguments


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="edmcgs poses", description="Estimate the camera's poses from a recording's frames (structure "
        "from motion over every APS / RGB frame) and write them as a TUM trajectory: one line "
        "'t tx ty tz qx qy qz qw' per registered frame, t in seconds on the recording's clock, OpenCV "
        "camera-to-world (x right, y down, z forward), the world the first registered frame's camera, the "
        "scale such that the scene's median depth is 1. A camera that did not move is written as one pose.")
    parser.add_argument("recording", help="the recording: AEDAT4 (events and frames, or frames alone), "
                                          "or HDF5")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the TUM trajectory to write")
    parser.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(parser, split=False, poses=False)
    args = parser.parse_args(argv)
    if args.output.exists() and not args.force:
        parser.error(f"{args.output} exists (use --force to replace it)")
    from edmcgs.pipeline import estimated_poses, open_recording, write_tum

    try:
        rec = open_recording(args.recording, RecordingOptions.from_args(args), progress=not args.quiet)
        had_camera = rec.intrinsics is not None
        rec = estimated_poses(rec, progress=not args.quiet)
        write_tum(args.output, rec.trajectory_t_us, rec.trajectory_c2w)
    except EdmcgsError as exc:
        print(f"edmcgs poses: {exc}", file=sys.stderr)
        return 1
    count = len(rec.trajectory_t_us)
    print(f"wrote {args.output}: {count} pose{'' if count == 1 else 's'}")
    if rec.intrinsics is not None and not had_camera:
        fx, fy, cx, cy = rec.intrinsics
        print(f"the estimated camera, for --intrinsics: {fx:.3f},{fy:.3f},{cx:.3f},{cy:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
