"""``edmcgs warm-up``: compile the numba kernels once, into numba's on-disk cache, so that the first
``edmcgs-serve``, ``edmcgs train`` and ``edmcgs synth`` start at once instead of compiling for tens of
seconds (setup runs it: ``scripts/bootstrap.sh``).

Each path runs as it does for real, on the bundled demo scene, so numba caches the very signatures those
commands call: the service opened and closed (renderer, event maps, the projection onto the events,
frame encoding), two training steps of a small model on the demo's recording and its baselines (as a
run ends), and the event simulator over a few milliseconds of a synthetic scene. Where the cache already
holds them this takes seconds.
"""

from __future__ import annotations

import argparse
import sys
import time


def _serve() -> None:
    from edmcgs.server.service import Service
    from edmcgs.server.settings import Settings

    Service.open(Settings.model_construct()).close()  # the defaults (the demo), whatever EDMCGS_* says


def _train() -> None:
    from edmcgs.model.eval.baselines import score_baselines
    from edmcgs.model.train.trainer import Trainer
    from edmcgs.pipeline import build_config, new_model, training_data
    from edmcgs.sensor.files.recording import read_recording
    from edmcgs.server import demo

    rec = read_recording(demo.files()[1])
    data = training_data(rec)
    trainer = Trainer(new_model(data, build_config("demo", ["init_points=2000"], rec)), data,
                      progress=False)
    for _ in range(2):
        trainer.train_step()
    score_baselines(data, data.evaluable()[:1])  # the end of a run: its baselines (events onto a frame)


def _synth() -> None:
    from edmcgs.synth.build import BuildConfig, build_recording

    build_recording(BuildConfig("jumpingjack", fps=50, duration_s=0.02, held_out_per_interval=0),
                    progress=False)


PATHS = {"serve": _serve, "train": _train, "synth": _synth}
"""What each command compiles, by the command."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="edmcgs warm-up", description=__doc__.split("\n\n")[0])
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    args = parser.parse_args(argv)
    import torch
    from tqdm import tqdm

    from edmcgs.errors import EdmcgsError

    torch.set_num_threads(1)
    took = {}
    with tqdm(PATHS.items(), desc="compiling the numba kernels", unit="path", disable=args.quiet,
              file=sys.stderr) as bar:
        for name, run in bar:
            bar.set_postfix_str(name)
            started = time.perf_counter()
            try:
                run()
            except EdmcgsError as exc:
                print(f"edmcgs warm-up: {name}: {exc}", file=sys.stderr)
                return 1
            took[name] = time.perf_counter() - started
    if not args.quiet:
        print(f"numba kernels in the cache ({sum(took.values()):.1f} s: "
              + ", ".join(f"{name} {seconds:.1f} s" for name, seconds in took.items()) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
