"""``edmcgs train RECORDING -o CKPT``: fit EdMCGS to a recording (an application edge: reads the
recording with ``edmcgs.sensor`` and hands the model plain arrays plus an event-map callable)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from edmcgs.errors import EdmcgsError, InvalidInputError, TrainingError
from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.model.config import PRESETS, EdmcgsConfig, preset
from edmcgs.model.motion.leanness import events_decision
from edmcgs.model.train.data import TrainingData
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import Recording, read_recording

STRUCTURAL = ("events", "markov", "sh_degree", "num_control_points", "skin_k", "graph_k", "deform_width",
              "deform_depth", "pos_freqs", "time_freqs", "event_pos_freqs", "event_hidden")
"""Config fields that shape the parameters: a resumed run cannot change them."""


def recording_intrinsics(rec: Recording) -> Intrinsics:
    """The recording's pinhole camera; without one, a centred camera with a 53-degree horizontal view."""
    if rec.intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in rec.intrinsics)
        return Intrinsics(fx, fy, cx, cy, rec.width, rec.height)
    print("warning: the recording has no intrinsics; assuming fx = fy = width, centred principal point",
          file=sys.stderr)
    return Intrinsics(float(rec.width), float(rec.width), (rec.width - 1) / 2, (rec.height - 1) / 2,
                      rec.width, rec.height)


def training_data(rec: Recording) -> TrainingData:
    """Turn a recording into the model's arrays; poses default to the trajectory, then to a static camera."""
    anchors = rec.anchors
    if len(anchors) == 0:
        raise TrainingError("the recording has no anchor frames: EdMCGS needs at least one RGB/APS frame")
    if (anchors.width, anchors.height) != (rec.width, rec.height):
        raise TrainingError("anchor frames and events differ in resolution; resample the frames first")
    if rec.trajectory_t_us is not None:
        trajectory = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w)
    elif anchors.poses is not None:
        trajectory = Trajectory(anchors.t_us, anchors.poses)
    else:
        trajectory = Trajectory(anchors.t_us[:1], np.eye(4)[None])
    poses = anchors.poses if anchors.poses is not None else trajectory.at(anchors.t_us)
    ends = [int(anchors.t_us[-1])]
    if len(rec.events):
        ends.append(int(rec.events.t_end) + 1)
    held = rec.held_out
    if held is not None and len(held):
        ends.append(int(held.t_us[-1]))
    width, height, events = rec.width, rec.height, rec.events

    def event_map(t0_us: int, t1_us: int) -> np.ndarray:
        return accumulate(events.time_slice(t0_us, t1_us), width, height)

    return TrainingData(
        anchors_t_us=anchors.t_us, anchor_images=anchors.images, anchor_poses=poses,
        intrinsics=recording_intrinsics(rec), trajectory=trajectory, t_end_us=max(ends),
        event_map=event_map if len(events) else None, event_size=(width, height),
        held_out_t_us=None if held is None or not len(held) else held.t_us,
        held_out_images=None if held is None or not len(held) else held.images,
        held_out_poses=None if held is None or not len(held) else held.poses)


def build_config(name: str, overrides: list[str], rec: Recording) -> EdmcgsConfig:
    """Preset, then what the recording states (contrast threshold, a synthetic scene's constant
    background colour), then ``--set`` overrides, then what the data leaves out (no events: no event
    branch, said on stdout)."""
    cfg = preset(name)
    if rec.contrast_threshold is not None:
        cfg = cfg.replace(contrast_threshold=float(rec.contrast_threshold))
    background = rec.metadata.get("background")
    if isinstance(background, list) and len(background) == 3:
        cfg = cfg.replace(background=tuple(float(v) for v in background))
    cfg = cfg.with_overrides(overrides)
    events, message = events_decision(len(rec.events), cfg.events)
    if message is not None:
        print(f"edmcgs train: {message}")
        cfg = cfg.replace(events=events)
    return cfg


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs train", description="Train EdMCGS on a recording.")
    parser.add_argument("recording", help="HDF5 recording (edmcgs format) with anchors and events")
    parser.add_argument("-o", "--output", required=True, help="checkpoint to write (atomically)")
    parser.add_argument("--config", default="demo", choices=sorted(PRESETS), help="preset (default: demo)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config field, e.g. --set events=false --set iterations=500")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoint at --output")
    parser.add_argument("--history", help="write the periodic held-out evaluation to this CSV")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: on a CPU shared with other work, OpenMP threads "
                             "that spin-wait for each other are many times slower than one thread)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs train: {exc}", file=sys.stderr)
        return 1


def _run(args) -> int:
    import torch

    from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
    from edmcgs.model.dynamic import EdMCGS
    from edmcgs.model.eval.evaluation import evaluate, summarize
    from edmcgs.model.train.trainer import Trainer, write_history_csv

    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    rec = read_recording(args.recording)
    data = training_data(rec)
    out = Path(args.output)
    train_state = None
    if args.resume and out.exists():
        payload = read_checkpoint(out)
        model = load_checkpoint(out)
        cfg = model.config.with_overrides(args.overrides)
        changed = [k for k in STRUCTURAL if getattr(cfg, k) != getattr(model.config, k)]
        if changed:
            raise InvalidInputError(f"--resume cannot change {changed}: they shape the saved parameters")
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
    summary = summarize(evaluate(trainer.model, data))
    print(f"{written}; held-out PSNR {summary['psnr']:.2f} dB, SSIM {summary['ssim']:.4f} "
          f"over {summary['frames']} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
