"""``edmcgs export-ply CKPT --t T -o scene.ply [--recording REC]``: the deformed Gaussians at time t in the
3DGS PLY layout (``edmcgs.model.ply``), for SuperSplat, gsplat's viewer or SIBR.

With ``--recording`` (the checkpoint's own, any format ``edmcgs train`` reads) the events over
[tau(t), t) drive the event branch as they do when serving; without it the event branch sees no events
(the time prior alone), which the command says.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs export-ply", description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="EdMCGS checkpoint")
    when = parser.add_mutually_exclusive_group(required=True)
    when.add_argument("--t", type=float, help="time in seconds from the checkpoint's first anchor")
    when.add_argument("--t-us", type=int, help="absolute time in microseconds (the recording's clock)")
    parser.add_argument("-o", "--output", required=True, type=Path, help="PLY file to write (atomically)")
    parser.add_argument("--recording", help="the checkpoint's recording: its events drive the event branch")
    parser.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")
    parser.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    args = parser.parse_args(argv)
    if args.output.exists() and not args.force:
        parser.error(f"{args.output} exists (use --force to replace it)")
    try:
        check_checkpoint(args.checkpoint, verify=True, hint="give it as --recording (the checkpoint first)")
        if args.recording is not None:
            check_recording(args.recording, hint="the checkpoint goes first; --recording takes its recording")
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs export-ply: {exc}", file=sys.stderr)
        return 1


def _run(args) -> int:
    import math

    import numpy as np

    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.ply import write_ply
    from edmcgs.options import RecordingOptions
    from edmcgs.pipeline import open_recording, training_data
    from edmcgs.protocol import t_us_of_seconds

    model = load_checkpoint(args.checkpoint)
    meta = model.meta
    if args.t is not None and not math.isfinite(args.t):
        raise InvalidInputError(f"--t must be a finite number of seconds, got {args.t}")
    t_us = args.t_us if args.t is None else t_us_of_seconds(args.t, meta.t_start_us)
    if not meta.t_start_us <= t_us <= meta.t_end_us:
        raise InvalidInputError(f"t = {(t_us - meta.t_start_us) / 1e6:g} s is outside the checkpoint's span "
                                f"0..{(meta.t_end_us - meta.t_start_us) / 1e6:g} s")
    emap = None
    tau = model.tau(t_us)
    if args.recording is not None:
        data = training_data(open_recording(args.recording, RecordingOptions()))
        if data.event_map is not None and t_us > tau:
            emap = np.asarray(data.event_map(tau, t_us), dtype=np.float32)
    elif model.transition is not None and t_us > tau and not args.quiet:
        print("no --recording: the event branch sees no events (the time prior alone)")
    state = model.deform(t_us, emap)
    write_ply(state, args.output)
    if args.quiet:
        return 0
    if model.bg_layer is not None:
        print("the checkpoint's distant background layer is not a set of Gaussians: it is not in the PLY")
    events = 0 if emap is None else int(np.abs(emap).sum())
    print(f"wrote {args.output}: {len(state)} Gaussians at t = {(t_us - meta.t_start_us) / 1e6:.6f} s "
          f"(anchor {(tau - meta.t_start_us) / 1e6:.6f} s, {events} events)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
