"""``edmcgs train RECORDING -o CKPT``: fit EdMCGS to a recording (an application edge: the recording
becomes training data and config through ``edmcgs.pipeline``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.model.config import PRESETS
from edmcgs.options import RecordingOptions, add_recording_arguments


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs train", description="Train EdMCGS on a recording.")
    parser.add_argument("recording", nargs="?", help="the recording: AEDAT4, or HDF5 (edmcgs, DSEC, v2e)")
    parser.add_argument("-o", "--output", help="checkpoint to write (atomically)")
    parser.add_argument("--list-config", action="store_true",
                        help="print every config key of the preset, by part, with its value and description, "
                             "then exit")
    parser.add_argument("--config", default="demo", choices=sorted(PRESETS), help="preset (default: demo)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config field, e.g. --set events=false --set iterations=500")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint at --output")
    parser.add_argument("--history", help="write the periodic held-out evaluation to this CSV")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: on a CPU shared with other work, OpenMP threads "
                             "that spin-wait for each other are many times slower than one thread)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(parser)
    args = parser.parse_args(argv)
    if args.list_config:
        return _list_config(args.config)
    if args.recording is None or args.output is None:
        parser.error("give RECORDING and -o CHECKPOINT (or --list-config)")
    try:
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs train: {exc}", file=sys.stderr)
        return 1


def _list_config(name: str) -> int:
    import textwrap
    from dataclasses import fields

    from edmcgs.model.config import FROZEN_PARTS, PARTS, field_docs, preset

    cfg, docs = preset(name), field_docs()
    for part in PARTS:
        frozen = " (frozen on --resume)" if part in FROZEN_PARTS else ""
        print(textwrap.fill(f"{part.__name__}{frozen}: {' '.join(part.__doc__.split())}", 100,
                            initial_indent="# ", subsequent_indent="# ") + "\n")
        for f in fields(part):
            print(f"{f.name} = {getattr(cfg, f.name)!r}\n    {docs[f.name]}")
        print()
    return 0


def check_resume_fits(model, data, path) -> None:
    """InvalidInputError unless the checkpoint at ``path`` was trained on this recording's anchors, camera
    and event maps (``--resume`` would otherwise overwrite it, then fail)."""
    import numpy as np

    meta = model.meta
    problems = []
    if not np.array_equal(np.asarray(meta.anchors_us), np.asarray(data.anchors_t_us)):
        problems.append(f"anchors ({len(meta.anchors_us)} in the checkpoint, {len(data.anchors_t_us)} in the "
                        "recording, or at other times)")
    if (meta.intrinsics.width, meta.intrinsics.height) != (data.intrinsics.width, data.intrinsics.height):
        problems.append(f"camera {meta.intrinsics.width}x{meta.intrinsics.height} vs "
                        f"{data.intrinsics.width}x{data.intrinsics.height}")
    if data.event_size is not None and tuple(data.event_size) != (meta.event_width, meta.event_height):
        problems.append(f"event maps {meta.event_width}x{meta.event_height} vs "
                        f"{data.event_size[0]}x{data.event_size[1]}")
    channels = 1 if data.anchor_images.ndim == 3 else int(data.anchor_images.shape[-1])
    if channels != meta.channels:
        problems.append(f"{meta.channels} vs {channels} colour channels")
    if int(data.t_end_us) != int(meta.t_end_us):
        problems.append(f"span end {meta.t_end_us} vs {data.t_end_us} µs")
    if problems:
        raise InvalidInputError(f"--resume: {path} was not trained on this recording "
                                f"({'; '.join(problems)}); it was left as it is. Train to another --output, "
                                "or give its recording")


def _run(args) -> int:
    import torch

    from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
    from edmcgs.model.devices import check_device
    from edmcgs.model.dynamic import EdMCGS
    from edmcgs.model.eval.baselines import BASELINES, score_baselines
    from edmcgs.model.eval.compare import Comparison
    from edmcgs.model.eval.evaluation import evaluate
    from edmcgs.model.train.trainer import Trainer, write_history_csv
    from edmcgs.pipeline import build_config, open_recording, training_data

    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    check_device(args.device)
    rec = open_recording(args.recording, RecordingOptions.from_args(args), progress=not args.quiet)
    if rec.trajectory_t_us is None and rec.anchors.poses is None:
        print("no camera poses in the recording: a static camera (give --poses TRAJ.txt for a moving one)")
    if rec.held_out is None or not len(rec.held_out):
        print(f"{len(rec.anchors)} anchors and no held-out frames (--anchor-fps F or --anchor-every N keeps "
              "the frames between anchors as held-out ground truth)")
    data = training_data(rec)
    out = Path(args.output)
    train_state = None
    if args.resume and out.exists():
        payload = read_checkpoint(out)
        model = load_checkpoint(out)
        check_resume_fits(model, data, out)  # before anything is written over it
        cfg = model.config.with_overrides(args.overrides)
        changed = model.config.frozen_changes(cfg)
        if changed:
            raise InvalidInputError(f"--resume cannot change {changed}: the saved tensors were built with "
                                    "them (the config's Structure and Initialisation parts; --list-config)")
        model.config = cfg
        model.meta.config = cfg.to_dict()
        train_state = payload.get("train_state")
        print(f"resuming from {out}" + ("" if train_state else " (no optimizer state: a fresh optimizer)"))
    else:
        cfg = build_config(args.config, args.overrides, rec)
        model = EdMCGS.from_arrays(anchors_t_us=data.anchors_t_us, anchor_images=data.anchor_images,
                                   intrinsics=data.intrinsics, anchor_poses=data.anchor_poses,
                                   t_end_us=data.t_end_us, trajectory=data.trajectory,
                                   event_size=data.event_size, config=cfg)
    trainer = Trainer(model, data, device=args.device, progress=not args.quiet)
    if train_state:
        trainer.load_train_state(train_state)
    history = trainer.fit(out)
    if args.history:
        write_history_csv(history, args.history)
    written = f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, {len(trainer.model.gaussians)} Gaussians)"
    if not data.evaluable().size:
        print(f"{written}; the recording has no held-out frames to score it on")
        return 0
    comparison = Comparison({"model": evaluate(trainer.model, data), **score_baselines(data)})
    summary = comparison.summary()
    model = summary.pop("model")
    baselines = ", ".join(f"{name}: {s['psnr']:.2f} dB / {s['ssim']:.4f}" for name, s in summary.items())
    print(f"{written}; held-out PSNR {model['psnr']:.2f} dB, SSIM {model['ssim']:.4f} over {model['frames']} "
          f"frames; {baselines}")
    for line in comparison.losses("model", BASELINES):
        print(f"WARNING: the {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
