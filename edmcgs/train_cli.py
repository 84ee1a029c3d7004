"""``edmcgs train RECORDING -o CKPT``: fit EdMCGS to a recording (an application edge: the recording
becomes training data and config through ``edmcgs.pipeline``).

``edmcgs train REC1 REC2 ... -o FOLDER [--ray]``: one run per recording, each checkpoint
``FOLDER/<recording's stem>.ckpt``; with ``--ray`` the runs are Ray tasks side by side (``--threads``
CPUs each; ``edmcgs.fanout``), else one after another.

``edmcgs train REC -o CKPT --ray --workers N``: one run of one recording, data-parallel over N Ray Train
workers (``edmcgs.data_parallel``), the same single checkpoint."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.filekind import check_checkpoint, check_recording
from edmcgs.model.config import PRESETS, split_overrides
from edmcgs.options import AUTO_POSES, RecordingOptions, add_recording_arguments


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs train", description="Train EdMCGS on a recording.")
    parser.add_argument("recording", nargs="*", help="the recording: AEDAT4, or HDF5 (edmcgs, DSEC, v2e); "
                                                     "several: one run each")
    parser.add_argument("-o", "--output", help="checkpoint to write (atomically); with several recordings "
                                               "or --ray (without --workers), a folder for one checkpoint "
                                               "per recording")
    parser.add_argument("--ray", action="store_true",
                        help="run each recording's training as a Ray task, or with --workers one recording's "
                             "training data-parallel (the 'ray' extra; joins --ray-address or RAY_ADDRESS, "
                             "else a local Ray)")
    parser.add_argument("--workers", type=int, metavar="N",
                        help="with --ray: train the one recording data-parallel on N Ray Train workers "
                             "(--threads CPUs each), each a shard of the anchor windows, the gradients "
                             "averaged every step; one checkpoint, as a single run writes")
    parser.add_argument("--ray-address", metavar="ADDR", help="the Ray cluster --ray joins (default: "
                                                              "RAY_ADDRESS, else a local Ray)")
    parser.add_argument("--ray-cpus", type=int, metavar="N", help="CPUs of the local Ray --ray starts")
    parser.add_argument("--list-config", action="store_true",
                        help="print every config key of the preset, by part, with its value and description, "
                             "then exit")
    parser.add_argument("--config", choices=sorted(PRESETS),
                        help="preset (default: moving for a camera that translates, with its poses and "
                             "points from --poses auto; else demo)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config field, e.g. --set events=false --set iterations=500")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--compile", action="store_true",
                        help="fuse the step's skinning, deformation networks and losses with "
                             "torch.compile: on the CPU about 1.3x faster steps after a compile of about a "
                             "minute (on a GPU not established); values equal to float32 rounding")
    parser.add_argument("--resume", nargs="?", const=True, default=None, metavar="CKPT",
                        help="continue the run saved in CKPT (default: the checkpoint at --output) with its "
                             "optimizer state, inside a checkpoint written mid-run (periodic or Ctrl-C) or "
                             "in the CKPT.train-state file beside a final one")
    parser.add_argument("--steps", type=int, metavar="N",
                        help="train N more steps from where the run stands (default: up to the config's "
                             "iterations; past them every schedule stays at its end)")
    parser.add_argument("--history", help="write the periodic held-out evaluation to this CSV")
    parser.add_argument("--tensorboard", metavar="DIR",
                        help="write training curves (losses, Gaussians, step time, held-out PSNR / SSIM) "
                             "for TensorBoard to DIR (the optional extra: pip install 'edmcgs[tensorboard]')")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: on a CPU shared with other work, OpenMP threads "
                             "that spin-wait for each other are many times slower than one thread)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true", help="replace OUTPUT if it exists (else --resume it)")
    add_recording_arguments(parser)
    args = parser.parse_args(argv)
    if args.list_config:
        return _list_config(args.config or "demo")
    if not args.recording or args.output is None:
        parser.error("give RECORDING and -o CHECKPOINT (or --list-config)")
    if args.workers is not None:
        if not args.ray:
            parser.error("--workers N trains data-parallel on Ray: give --ray too")
        if args.workers < 1 or len(args.recording) > 1:
            parser.error("--workers N (N >= 1) trains one recording")
        if args.resume is not None or args.steps is not None or args.tensorboard or args.compile:
            parser.error("--workers runs a whole training: --resume, --steps, --tensorboard and --compile "
                         "are for a single process")
    if args.ray_address:
        if not args.ray:
            parser.error("--ray-address ADDR goes with --ray")
        os.environ["RAY_ADDRESS"] = args.ray_address
    # -o is a folder: each checkpoint is checked in _run_many
    many = len(args.recording) > 1 or (args.ray and args.workers is None)
    if not many and args.resume is None and not args.force and os.path.exists(args.output):
        parser.error(f"{args.output} exists: --force replaces it, --resume continues its run")
    if args.steps is not None and args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    if args.tensorboard:
        from edmcgs.model.train.curves import tensorboard_missing

        reason = tensorboard_missing()
        if reason:
            print(f"edmcgs train: {reason}", file=sys.stderr)
            return 1
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        check_inputs(args, many)
        if many:
            return _run_many(args)
        args.recording = args.recording[0]
        return _run(args) if args.workers is None else _run_parallel(args)
    except EdmcgsError as exc:
        print(f"edmcgs train: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # outside the training loop (reading the recording; a second Ctrl-C)
        print(f"edmcgs train: interrupted; {args.output} is as it was before", file=sys.stderr)
        return INTERRUPTED


INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as shells report it."""


def check_inputs(args: argparse.Namespace, many: bool) -> None:
    """What can be checked before torch is imported (seconds): the --set keys, every recording is one, a
    checkpoint to resume is one, a trajectory file exists. An EdmcgsError naming the first problem."""
    split_overrides(args.overrides)  # the keys; their values are parsed against the config they change
    for recording in args.recording:
        check_recording(recording, hint="edmcgs train takes the recording to train on (a checkpoint goes to "
                                        "--resume)")
    resumed = args.resume if isinstance(args.resume, str) else None
    if args.resume is True and os.path.exists(args.output):
        resumed = args.output
    if resumed is not None and not many:  # several: --resume CKPT is refused, each run reads its own
        check_checkpoint(resumed, verify=True, hint="--resume takes the checkpoint of the run to continue")
    if args.poses not in (None, AUTO_POSES) and not os.path.isfile(args.poses):
        raise InvalidInputError(f"--poses {args.poses}: no such file")


def resume_command(argv: list[str], checkpoint, steps: int | None) -> str:
    """The command line that continues a run started with ``argv`` (the arguments after ``edmcgs
    train``) from ``checkpoint``: the same arguments, its own ``--resume`` / ``--steps`` replaced."""
    import shlex

    kept, i = [], 0
    while i < len(argv):
        arg = argv[i]
        name = arg.split("=", 1)[0]
        if name in ("--resume", "--steps"):
            takes = "=" not in arg and i + 1 < len(argv)
            if name == "--resume":  # an optional value: taken when it does not look like an option
                takes = takes and not argv[i + 1].startswith("-")
            i += 2 if takes else 1
            continue
        kept.append(arg)
        i += 1
    kept += ["--resume", str(checkpoint)] + ([] if steps is None else ["--steps", str(steps)])
    return "edmcgs train " + shlex.join(kept)


def _train_one(args: argparse.Namespace) -> int:
    """One recording's run (a Ray task's body with --ray): its exit code, its errors printed."""
    try:
        return _run(args)
    except EdmcgsError as exc:
        print(f"edmcgs train {args.recording}: {exc}", file=sys.stderr)
        return 1


def _shared_argv(args: argparse.Namespace) -> list[str]:
    """The command line's arguments that every recording's run shares (for its resume hint): without
    the recordings, the output and the Ray flags."""
    drop_with_value = {"-o", "--output", "--ray-cpus", "--ray-address", "--tensorboard"}
    out, skip = [], False
    for arg in args.argv:
        if skip:
            skip = False
        elif arg in drop_with_value:
            skip = True
        elif arg == "--ray" or arg in args.recording or arg.split("=", 1)[0] in drop_with_value:
            continue
        else:
            out.append(arg)
    return out


def _run_many(args: argparse.Namespace) -> int:
    """One run per recording into the folder ``--output``; the worst exit code."""
    folder = Path(args.output)
    if folder.exists() and not folder.is_dir():
        raise InvalidInputError(f"with several recordings (or --ray), -o is a folder for their checkpoints; "
                                f"{str(folder)!r} is a file")
    if args.history:
        raise InvalidInputError("--history takes one recording; with several, train them one at a time")
    if args.resume not in (None, True):
        raise InvalidInputError("--resume CKPT takes one recording; with several, a bare --resume continues "
                                "each from its own checkpoint in the output folder")
    stems = [Path(r).stem for r in args.recording]
    twice = sorted({s for s in stems if stems.count(s) > 1})
    if twice:
        raise InvalidInputError(f"two recordings share the name {', '.join(twice)}: their checkpoints "
                                "would overwrite each other in the output folder")
    existing = [str(folder / f"{stem}.ckpt") for stem in stems if (folder / f"{stem}.ckpt").exists()]
    if existing and args.resume is None and not args.force:
        raise InvalidInputError(f"{', '.join(existing)} exist(s): --force replaces them, --resume continues "
                                "their runs")
    folder.mkdir(parents=True, exist_ok=True)
    jobs = []
    for rec, stem in zip(args.recording, stems, strict=True):
        output = str(folder / f"{stem}.ckpt")
        curves = None if args.tensorboard is None else str(Path(args.tensorboard) / stem)  # one run each
        argv = [rec, "-o", output, *_shared_argv(args), *(["--tensorboard", curves] if curves else [])]
        jobs.append(argparse.Namespace(**{**vars(args), "recording": rec, "output": output, "argv": argv,
                                          "quiet": args.quiet or args.ray, "tensorboard": curves}))
    if args.ray:
        from edmcgs.fanout import fan_out

        codes = fan_out(_train_one, jobs, threads=args.threads, num_cpus=args.ray_cpus)
    else:
        codes = [_train_one(job) for job in jobs]
    for job, code in zip(jobs, codes, strict=True):
        print(f"{job.recording}: {'wrote ' + job.output if code == 0 else 'FAILED'}")
    return max(codes)


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


def _announce_compile() -> None:
    """One line before a run that compiles numba kernels first (the training ones, and the renderer's for
    the held-out scores at its end), which would otherwise sit at 0 % for tens of seconds."""
    from edmcgs.model.render import rasterize, rasterize_fast
    from edmcgs.model.render.jit import compiled

    seconds = sum(m.COMPILE_S for m in (rasterize, rasterize_fast) if not compiled(*m.KERNELS))
    if seconds:
        print(f"compiling the numba kernels (first run only, about {seconds} s; edmcgs warm-up does it "
              "ahead) ...", flush=True)


def _on_interrupt(stop: threading.Event):
    """SIGINT handler: the first Ctrl-C asks the trainer to stop after the current step and save; a second
    one abandons the run at once (a checkpoint being written is left out: writes are atomic)."""
    def handler(signum, frame) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        print("\nCtrl-C: finishing this step, then saving a resumable checkpoint (Ctrl-C again to abandon "
              "the run without saving)", file=sys.stderr, flush=True)
    return handler


def _run(args) -> int:
    import torch

    from edmcgs.model.checkpoint import load_checkpoint, read_checkpoint
    from edmcgs.model.devices import check_device
    from edmcgs.model.train.curves import TensorBoardCurves
    from edmcgs.model.train.resume import resume_state
    from edmcgs.model.train.trainer import Trainer, write_history_csv
    from edmcgs.pipeline import build_config, default_preset, new_model, open_recording, training_data

    if args.threads < 1:
        raise InvalidInputError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    check_device(args.device)
    rec = open_recording(args.recording, RecordingOptions.from_args(args), progress=not args.quiet,
                         lazy_events=True)
    if rec.trajectory_t_us is None and rec.anchors.poses is None:
        print("no camera poses in the recording: a static camera (give --poses TRAJ.txt for a moving one)")
    if rec.held_out is None or not len(rec.held_out):
        print(f"{len(rec.anchors)} anchors and no held-out frames (--anchor-fps F or --anchor-every N keeps "
              "the frames between anchors as held-out ground truth)")
    data = training_data(rec)
    out = Path(args.output)
    source = out if args.resume is True else Path(args.resume) if args.resume else None
    train_state = None
    if source is not None and (source.exists() or args.resume is not True):
        payload = read_checkpoint(source)
        model = load_checkpoint(source)
        check_resume_fits(model, data, source)  # before anything is written over it
        cfg = model.config.with_overrides(args.overrides)
        changed = model.config.frozen_changes(cfg)
        if changed:
            raise InvalidInputError(f"--resume cannot change {changed}: the saved tensors were built with "
                                    "them (the config's Structure and Initialisation parts; --list-config)")
        train_state, origin = resume_state(source, payload)
        model.config = cfg
        model.meta.config = cfg.to_dict()
        model.meta.frozen = None  # a final checkpoint's still control points: decided again at the end
        print(f"resuming from {source} with {origin}"
              + (f", at step {int(train_state['step'])}" if train_state else ""))
    else:
        if source is not None:
            print(f"--resume: no checkpoint at {out} yet: training from the start")
        preset = args.config
        if preset is None:
            preset, why = default_preset(rec)
            print(f"--config {preset}: {why} (--config NAME chooses another)")
        cfg = build_config(preset, args.overrides, rec)
        model = new_model(data, cfg)
    if args.device == "cpu":
        _announce_compile()
    trainer = Trainer(model, data, device=args.device, progress=not args.quiet, compile=args.compile)
    if train_state:
        trainer.load_train_state(train_state)
    until = trainer.total_steps if args.steps is None else trainer.step + args.steps
    if trainer.step >= until:
        raise InvalidInputError(f"{source} is already at step {trainer.step} of {trainer.total_steps}: give "
                                "--steps N to train N more (or --set iterations=M for a longer schedule)")
    curves = None
    if args.tensorboard:
        curves = TensorBoardCurves(args.tensorboard, purge_step=trainer.step + 1)
    stop = threading.Event()
    handle = threading.current_thread() is threading.main_thread()  # signal handlers live there only
    previous = signal.signal(signal.SIGINT, _on_interrupt(stop)) if handle else None
    try:
        history = trainer.fit(out, until=until, stop=stop, curves=curves)
    except KeyboardInterrupt:  # the second Ctrl-C
        # what the file holds, read back: the interrupt may have cut a save after its rename, before the
        # trainer noted the step
        held = _held_step(out)
        held = trainer.saved_step if held is None else held
        saved = f"{out} holds step {held}" if held is not None else \
            f"nothing was saved by this run ({out} is as it was before)"
        print(f"edmcgs train: abandoned at step {trainer.step}; {saved}", file=sys.stderr)
        curves = None  # the interrupt may have landed inside its writer, whose close could then wait forever;
        # what it holds up to the last checkpoint is on disk already, and its thread is a daemon
        return INTERRUPTED
    finally:
        if handle:
            signal.signal(signal.SIGINT, previous)
        if curves is not None:
            curves.close()
    if args.history:
        write_history_csv(history, args.history)
    if trainer.interrupted:
        more = None if until == trainer.total_steps else until - trainer.step
        print(f"interrupted at step {trainer.step} of {until}: saved a resumable checkpoint to {out}; "
              f"continue with: {resume_command(args.argv, out, more)}", file=sys.stderr)
        return INTERRUPTED
    return _report(trainer.model, data, out)


def _held_step(path) -> int | None:
    """The training step of the checkpoint at ``path`` (None: none there, or one without its state)."""
    from edmcgs.model.checkpoint import read_checkpoint

    try:
        return int(read_checkpoint(path)["train_state"]["step"])
    except (EdmcgsError, OSError, KeyError, TypeError, ValueError):
        return None


def _run_parallel(args) -> int:
    """One recording trained data-parallel on ``args.workers`` Ray Train workers, then scored here."""
    from dataclasses import replace

    from edmcgs.data_parallel import Job, train
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.pipeline import open_recording, training_data

    if args.device != "cpu":
        raise InvalidInputError("--workers trains on the CPU (gloo); leave out --device")
    # Ray's workers run elsewhere (another directory, on a cluster another machine): absolute paths.
    options = RecordingOptions.from_args(args)
    files = {name: os.path.abspath(value) for name in ("poses", "intrinsics")
             if (value := getattr(options, name)) is not None and os.path.isfile(value)}
    job = Job(recording=os.path.abspath(args.recording), output=os.path.abspath(args.output),
              config=args.config, overrides=args.overrides, options=replace(options, **files),
              threads=args.threads, quiet=args.quiet,
              history=None if args.history is None else os.path.abspath(args.history))
    print(f"training {args.recording} on {args.workers} Ray Train worker(s), {args.threads} thread(s) each")
    train(job, args.workers, num_cpus=args.ray_cpus)
    data = training_data(open_recording(job.recording, job.options, lazy_events=True))
    return _report(load_checkpoint(args.output), data, Path(args.output))


def _report(model, data, out: Path) -> int:
    """The line a finished run prints: the checkpoint, and its held-out scores beside the baselines."""
    from edmcgs.model.eval.baselines import BASELINES, score_baselines
    from edmcgs.model.eval.compare import Comparison
    from edmcgs.model.eval.evaluation import evaluate

    written = f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, {len(model.gaussians)} Gaussians)"
    if not data.evaluable().size:
        print(f"{written}; the recording has no held-out frames to score it on")
        return 0
    comparison = Comparison({"model": evaluate(model, data), **score_baselines(data)})
    summary = comparison.summary()
    ours = summary.pop("model")
    baselines = ", ".join(f"{name}: {s['psnr']:.2f} dB / {s['ssim']:.4f}" for name, s in summary.items())
    print(f"{written}; held-out PSNR {ours['psnr']:.2f} dB, SSIM {ours['ssim']:.4f} (3DGS convention "
          f"{ours['ssim_3dgs']:.4f}) over {ours['frames']} frames; {baselines}")
    for line in comparison.losses("model", BASELINES):
        print(f"WARNING: the {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
