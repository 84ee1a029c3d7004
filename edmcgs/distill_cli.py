"""``edmcgs distill CKPT RECORDING -o OUT``: give a checkpoint the event transition its online anchors use
past its span, learnt from its own motion over the span (``edmcgs.model.online.distill``).

RECORDING is the one the checkpoint was trained on (any format ``edmcgs train`` reads, with the same
flags): its events over the span are the inputs. The written checkpoint is the input's with
``online_transition`` added (or replaced); ``edmcgs-serve`` offers it past the span
(EDMCGS_ONLINE_TRANSITION).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording
from edmcgs.options import RecordingOptions, add_recording_arguments


def main(argv: list[str] | None = None) -> int:
    from edmcgs.model.online import distill as online_distill

    parser = argparse.ArgumentParser(prog="edmcgs distill", description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="EdMCGS checkpoint with an event branch")
    parser.add_argument("recording", help="the recording it was trained on")
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="checkpoint to write (atomically; may be CHECKPOINT itself with --force)")
    parser.add_argument("--samples", type=int, default=online_distill.SAMPLES,
                        help=f"times sampled over the span (default {online_distill.SAMPLES})")
    parser.add_argument("--steps", type=int, default=online_distill.STEPS,
                        help=f"Adam steps (default {online_distill.STEPS})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summary")
    add_recording_arguments(parser, split=False)
    args = parser.parse_args(argv)
    if args.output.exists() and not args.force:
        parser.error(f"{args.output} exists (use --force to replace it)")
    try:
        order = "edmcgs distill takes the checkpoint first, then the recording it was trained on"
        check_checkpoint(args.checkpoint, verify=True, hint=order)
        check_recording(args.recording, hint=order)
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs distill: {exc}", file=sys.stderr)
        return 1


def _run(args) -> int:
    import time

    import torch

    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.online.distill import distill, save_with
    from edmcgs.pipeline import open_recording, training_data

    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    model = load_checkpoint(args.checkpoint)
    model.requires_grad_(False)
    data = training_data(open_recording(args.recording, RecordingOptions.from_args(args)))
    meta = model.meta
    if data.event_map is None:
        raise InvalidInputError(f"{args.recording} has no events")
    size = data.event_size or (data.intrinsics.width, data.intrinsics.height)
    if tuple(size) != (meta.event_width, meta.event_height):
        raise InvalidInputError(f"{args.recording}'s events are {size[0]}x{size[1]}, the checkpoint's "
                                f"{meta.event_width}x{meta.event_height}: is it the checkpoint's recording?")
    started = time.perf_counter()
    out = distill(model, data.event_map, samples=args.samples, steps=args.steps, seed=args.seed,
                  progress=not args.quiet)
    save_with(model, out.transition, args.output)
    if not args.quiet:
        mse = out.held_out_mse
        print(f"wrote {args.output}: online transition distilled from {out.samples} times of the span in "
              f"{time.perf_counter() - started:.1f} s; held-out displacement error (mean squared, scene "
              f"extents^2): {mse['distilled']:.3g} distilled, {mse['g_phi']:.3g} g_phi as trained, "
              f"{mse['still']:.3g} standing still")
    return 0


if __name__ == "__main__":
    sys.exit(main())
