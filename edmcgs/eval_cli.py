"""``edmcgs eval CKPT RECORDING [--csv PATH]`` (or ``edmcgs eval --demo``): PSNR / SSIM of a checkpoint at
a recording's held-out frames (an application edge: the recording is read with ``edmcgs.sensor``)."""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import replace

from edmcgs.atomic import atomic_output
from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording
from edmcgs.options import AUTO_POSES, RecordingOptions, add_recording_arguments


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs eval",
                                     description="Evaluate a checkpoint on held-out frames.")
    parser.add_argument("checkpoint", nargs="?", help="EdMCGS checkpoint")
    parser.add_argument("recording", nargs="?",
                        help="the recording it was trained on (AEDAT4 or HDF5); the frames that are not the "
                             "checkpoint's anchors are scored")
    parser.add_argument("--demo", action="store_true", help="evaluate the bundled demo scene")
    parser.add_argument("--csv", help="write one row per held-out frame here")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="only the comparison with the baselines (no per-frame table)")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--lpips-vgg", metavar="PTH",
                        help="torchvision's VGG-16 weights (vgg16-397923af.pth; default: torch's hub cache)")
    parser.add_argument("--lpips-lin", metavar="PTH",
                        help="LPIPS's weights/v0.1/vgg.pth (default: an installed lpips package's)")
    parser.add_argument("--reference-renderer", action="store_true",
                        help="render with the differentiable PyTorch rasterizer instead of the fast one")
    add_recording_arguments(parser, split=False)
    args = parser.parse_args(argv)
    if args.demo == bool(args.checkpoint or args.recording) or (args.checkpoint and not args.recording):
        parser.error("give CHECKPOINT RECORDING, or --demo alone")
    try:
        if args.demo:
            from edmcgs.server.demo import files

            args.checkpoint, args.recording = files()
        else:  # before torch: a wrong file is said at once
            order = "edmcgs eval takes the checkpoint first, then the recording it was trained on"
            check_checkpoint(args.checkpoint, verify=True, hint=order)
            check_recording(args.recording, hint=order)
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs eval: {exc}", file=sys.stderr)
        return 1


def _run(args) -> int:
    import numpy as np
    import torch

    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.devices import check_device
    from edmcgs.model.eval.baselines import BASELINES, SHORT, score_baselines
    from edmcgs.model.eval.compare import Comparison
    from edmcgs.model.eval.evaluation import evaluate, summarize
    from edmcgs.model.eval.lpips import LPIPS, find_weights, missing_weights
    from edmcgs.pipeline import open_recording, split_at, training_data, with_trajectory

    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    check_device(args.device)
    model = load_checkpoint(args.checkpoint, device=args.device)
    options = RecordingOptions.from_args(args)
    if options.poses == AUTO_POSES:  # the poses it was trained with, not a second estimate of them
        trajectory = model.meta.trajectory
        if trajectory is None:
            raise InvalidInputError(f"--poses auto: {args.checkpoint} stores no trajectory to score with")
        rec = with_trajectory(open_recording(args.recording, replace(options, poses=None), lazy_events=True),
                              trajectory.t_us, trajectory.c2w)
        print(f"--poses auto: the {len(trajectory)} poses {args.checkpoint} was trained with")
    else:
        rec = open_recording(args.recording, options, lazy_events=True)
    if not np.array_equal(rec.anchors.t_us, model.meta.anchors_us):
        rec = split_at(rec, model.meta.anchors_us)  # the split the checkpoint was trained with
    data = training_data(rec)
    if data.event_size != (model.meta.event_width, model.meta.event_height):
        raise InvalidInputError(f"event resolution {data.event_size} differs from the checkpoint's "
                                f"{(model.meta.event_width, model.meta.event_height)}")
    if data.held_out_t_us is None:
        raise InvalidInputError("the recording has no frames besides the checkpoint's anchors to evaluate on")
    weights = find_weights(args.lpips_vgg, args.lpips_lin)
    lpips = None if weights is None else LPIPS.load(*weights).to(args.device)
    rows = evaluate(model, data, fast=not args.reference_renderer, lpips=lpips)
    baselines = score_baselines(data, np.array([r.index for r in rows], dtype=np.int64))
    comparison = Comparison({"model": rows, **baselines})
    skipped = data.held_out_t_us.size - len(rows)
    if args.csv:
        with atomic_output(args.csv, InvalidInputError) as tmp, open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["index", "t_us", "anchor_us", "events", "psnr", "ssim", "lpips",
                             *(f"{m}_{SHORT[name]}" for name in BASELINES for m in ("psnr", "ssim")),
                             "ssim_3dgs"])
            for r, *base in zip(rows, *baselines.values(), strict=True):
                writer.writerow([r.index, r.t_us, r.anchor_us, r.events, f"{r.psnr:.4f}", f"{r.ssim:.5f}",
                                 "" if r.lpips is None else f"{r.lpips:.5f}",
                                 *(f"{v:{f}}" for b in base for v, f in ((b.psnr, ".4f"), (b.ssim, ".5f"))),
                                 f"{r.ssim_3dgs:.5f}"])
    summary = summarize(rows)
    if not args.quiet:
        _frame_table(rows, baselines, summary, model.meta.t_start_us, lpips is not None)
    print(comparison.markdown())
    print()
    for line in comparison.losses("model", BASELINES):
        print(f"WARNING: the {line}")
    if skipped:
        print(f"{skipped} held-out frame(s) outside the trained span were skipped")
    if not args.quiet:
        print(missing_weights(args.lpips_vgg, args.lpips_lin) if lpips is None
              else f"LPIPS (VGG) from {weights[0]} and {weights[1]}")
    return 0


def _frame_table(rows, baselines: dict, summary: dict, t0: int, lpips: bool) -> None:
    """One line per held-out frame: the model's scores beside each baseline's PSNR, then the means."""
    import numpy as np

    from edmcgs.model.eval.baselines import BASELINES, SHORT

    print("| frame | t (ms from first anchor) | events | PSNR (dB) | SSIM | SSIM (3DGS) |"
          + (" LPIPS |" if lpips else "") + "".join(f" {SHORT[name]}: PSNR |" for name in BASELINES))
    print("|---:|---:|---:|---:|---:|---:|" + ("---:|" if lpips else "") + "---:|" * len(BASELINES))
    for r, *base in zip(rows, *baselines.values(), strict=True):
        print(f"| {r.index} | {(r.t_us - t0) / 1000:.1f} | {r.events} | {r.psnr:.2f} | {r.ssim:.4f} "
              f"| {r.ssim_3dgs:.4f} |" + (f" {r.lpips:.4f} |" if lpips else "")
              + "".join(f" {b.psnr:.2f} |" for b in base))
    print(f"| **mean** ({summary['frames']} frames) | | | **{summary['psnr']:.2f}** "
          f"| **{summary['ssim']:.4f}** | **{summary['ssim_3dgs']:.4f}** |"
          + (f" **{summary['lpips']:.4f}** |" if lpips else "")
          + "".join(f" {np.mean([b.psnr for b in rows_b]):.2f} |" for rows_b in baselines.values()))
    print()


if __name__ == "__main__":
    sys.exit(main())
