"""What continuing a run needs besides the model: the trainer's state (step, optimizer moments, gradient
statistics, random generators, evaluation history).

A mid-training checkpoint carries it inside (``train_state``). A final checkpoint keeps it in a sidecar
file beside it, ``NAME.train-state``, so that the file a server loads stays the model alone; the sidecar
names the checkpoint it belongs to by its checksum, so a sidecar left from another run is never mixed in.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from edmcgs.atomic import atomic_output
from edmcgs.errors import CheckpointError

FORMAT = "edmcgs-train-state"
VERSION = 1
SUFFIX = ".train-state"


def sidecar_path(checkpoint: str | os.PathLike) -> Path:
    """Where a final checkpoint's train state lives: ``NAME.train-state`` beside it."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + SUFFIX)


def write_sidecar(checkpoint: str | os.PathLike, train_state: dict, checkpoint_checksum: str) -> Path:
    """Write ``train_state`` beside ``checkpoint`` (atomically), bound to the checkpoint's checksum."""
    path = sidecar_path(checkpoint)
    payload = {"format": FORMAT, "version": VERSION, "checkpoint": checkpoint_checksum,
               "train_state": train_state}
    with atomic_output(path, CheckpointError) as tmp:
        torch.save(payload, tmp)
    return path


def remove_sidecar(checkpoint: str | os.PathLike) -> None:
    """Remove the sidecar beside ``checkpoint``, if any."""
    sidecar_path(checkpoint).unlink(missing_ok=True)


def resume_state(checkpoint: str | os.PathLike, payload: dict) -> tuple[dict | None, str]:
    """The train state to continue from the checkpoint whose validated payload is ``payload``, and a
    phrase saying where it came from (or why there is none). A damaged sidecar, or one that belongs to
    another checkpoint, raises ``CheckpointError`` (removing it resumes with a fresh optimizer)."""
    embedded = payload.get("train_state")
    if embedded is not None:
        return embedded, "its optimizer state"
    path = sidecar_path(checkpoint)
    if not path.is_file():
        return None, f"no optimizer state (no {path.name} beside it): a fresh optimizer from step 0"
    remedy = f"remove {path} to resume with a fresh optimizer from step 0"
    try:
        side = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # torch raises UnpicklingError, RuntimeError, EOFError, zipfile errors ...
        # Never torch's message: it advises weights_only=False, i.e. running the file's code.
        raise CheckpointError(f"{path} is truncated, damaged or not a train-state file; it was not loaded "
                              f"({remedy})") from None
    if not isinstance(side, dict) or side.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an EdMCGS train-state file (no format {FORMAT!r}; {remedy})")
    if not isinstance(side.get("version"), int) or side["version"] > VERSION:
        raise CheckpointError(f"{path} has train-state version {side.get('version')!r}, not one this edmcgs "
                              f"reads ({VERSION}); upgrade edmcgs or {remedy}")
    if side.get("checkpoint") != payload.get("checksum"):
        raise CheckpointError(f"{path} belongs to another version of {checkpoint} (its checksum differs: "
                              f"a run stopped between the two writes, or a copied file); {remedy}")
    state = side.get("train_state")
    step = state.get("step") if isinstance(state, dict) else None
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(f"{path}: train_state.step must be an integer >= 0 ({remedy})")
    return state, f"the optimizer state in {path.name}"
