"""The bundled demo scene: a checkpoint and its recording shipped inside the package (server/demo/)."""

from __future__ import annotations

from pathlib import Path

from edmcgs.errors import CheckpointError

DEMO_DIR = Path(__file__).resolve().parent / "demo"
CHECKPOINT = DEMO_DIR / "scene.ckpt"
"""The trained demo checkpoint."""
RECORDING = DEMO_DIR / "scene.h5"
"""Its recording (our HDF5 format), replayed in real time in a loop."""


def files() -> tuple[Path, Path]:
    """(checkpoint, recording) of the demo, or CheckpointError saying how to get them."""
    missing = [p.name for p in (CHECKPOINT, RECORDING) if not p.is_file()]
    if missing:
        raise CheckpointError(
            f"the bundled demo scene is missing ({', '.join(missing)} in {DEMO_DIR}); this build ships "
            "without it. Serve your own scene with: edmcgs-serve --replay REC.h5 --checkpoint CKPT --loop "
            "(edmcgs synth builds a recording, edmcgs train a checkpoint)")
    return CHECKPOINT, RECORDING
