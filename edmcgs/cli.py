"""``edmcgs``: the command line, one subcommand per job, each living beside the code it drives."""

import argparse
import importlib
import sys

from edmcgs import __version__
from edmcgs.errors import did_you_mean

# subcommand -> (module, help). Imported lazily so that `edmcgs --help` is instant.
COMMANDS = {
    "record": ("edmcgs.record_cli", "record a live camera or a replay to AEDAT4 or HDF5"),
    "synth": ("edmcgs.synth.cli", "build a synthetic dynamic scene with simulated events"),
    "poses": ("edmcgs.poses_cli", "estimate the camera's poses from a recording's frames (a TUM file)"),
    "train": ("edmcgs.train_cli", "train EdMCGS on a recording"),
    "eval": ("edmcgs.eval_cli", "evaluate a checkpoint on a recording's held-out frames"),
    "distill": ("edmcgs.distill_cli", "learn the transition online anchors use past a checkpoint's span"),
    "export": ("edmcgs.clients.export", "export a time sweep of a running service as GIF or MP4"),
    "export-ply": ("edmcgs.export_ply_cli", "write the Gaussians at a time t as a 3DGS PLY file"),
    "warm-up": ("edmcgs.warmup_cli", "compile the numba kernels into numba's cache (setup runs it)"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "--version") or argv[0] not in COMMANDS:
        parser = argparse.ArgumentParser(prog="edmcgs", description="EdMCGS tools")
        parser.add_argument("--version", action="version", version=f"edmcgs {__version__}")
        parser.add_argument("command", choices=sorted(COMMANDS), help="; ".join(
            f"{name}: {text}" for name, (_, text) in COMMANDS.items()))
        if argv and argv[0] not in COMMANDS and not argv[0].startswith("-"):
            parser.error(f"unknown command {argv[0]!r}{did_you_mean(argv[0], COMMANDS)} (invalid choice; "
                         f"choose from {', '.join(sorted(COMMANDS))})")
        parser.parse_args(argv[:1])
        return 2
    if "--version" in argv[1:]:  # every subcommand answers it, the same way
        print(f"edmcgs {__version__}")
        return 0
    module = importlib.import_module(COMMANDS[argv[0]][0])
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
