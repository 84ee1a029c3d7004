"""What a user tells the commands about a recording that its file may not say, and the command-line
flags that say it. Light on purpose (no torch): a command parses its arguments before it loads the model,
so ``--help`` is instant; ``edmcgs.pipeline.open_recording`` applies the options."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

AUTO_POSES = "auto"
"""``--poses auto``: estimate the camera's poses from the recording's own frames (``edmcgs.poses``)."""


@dataclass(frozen=True)
class RecordingOptions:
    """What a user tells about a recording that its file may not say (the shared command-line flags)."""

    anchor_fps: float | None = None
    """Pick anchors at this rate among the frames; the others are held out."""
    anchor_every: int | None = None
    """Pick every N-th frame as an anchor (from the first); the others are held out."""
    intrinsics: str | None = None
    """``fx,fy,cx,cy`` in pixels, or a DV camera-calibration file (.json, or legacy .xml)."""
    poses: str | None = None
    """A TUM trajectory file (``t tx ty tz qx qy qz qw``: the quaternion's w last, where the server's
    ``pose=`` puts it first; t in seconds on the recording's clock), or ``auto``: structure from motion
    over the recording's frames."""
    resolution: str | None = None
    """``WIDTHxHEIGHT`` for HDF5 layouts that do not store it (DSEC, v2e)."""

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> RecordingOptions:
        return cls(**{k: getattr(args, k, None) for k in cls.__dataclass_fields__})


def add_recording_arguments(parser: argparse.ArgumentParser, *, split: bool = True,
                            resolution: bool = True, poses: bool = True) -> None:
    """The flags of ``RecordingOptions`` (``split=False``: without the anchor choice; ``resolution=False``
    for a parser that has its own ``--resolution``; ``poses=False`` for ``edmcgs poses``, which estimates
    them)."""
    if split:
        group = parser.add_mutually_exclusive_group()
        group.add_argument("--anchor-fps", type=float, metavar="F",
                           help="use frames at about F per second as anchors, the rest as held-out "
                                "ground truth")
        group.add_argument("--anchor-every", type=int, metavar="N",
                           help="use every N-th frame as an anchor, the rest as held-out ground truth")
    parser.add_argument("--intrinsics", metavar="FX,FY,CX,CY|CALIB.json",
                        help="the camera: pixels, or a DV camera-calibration file (default: the recording's)")
    if poses:
        parser.add_argument("--poses", metavar="TRAJ.txt|auto",
                            help="camera-to-world poses (OpenCV axes), TUM format: t tx ty tz qx qy qz qw, "
                                 "the quaternion's w LAST (GET /render's pose= and --pose take it first), t "
                                 "in seconds; or auto: estimated from the recording's frames by structure "
                                 "from motion (edmcgs eval: the poses the checkpoint was trained with; "
                                 "default: the recording's, else a static camera)")
    if resolution:
        parser.add_argument("--resolution", metavar="WxH",
                            help="HDF5 layouts without one (DSEC, v2e), e.g. 640x480")
