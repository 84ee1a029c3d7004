"""What continuing a run needs besides the model: the trainer's state (step, optimizer moments, gradient
statistics, random generators, evaluation history).

A mid-training checkpoint carries it inside (``train_state``). A final checkpoint keeps it in a sidecar
file beside it, ``NAME.train-state``, so that the file a server loads stays the model alone; the sidecar
names the checkpoint it belongs to by its checksum, so a sidecar left from another run is never mixed in.

The two files of a final save are one unit (``save_final``): the train state is written first, beside
the old sidecar as ``NAME.train-state.new``; the checkpoint's rename is the commit; then the new state
takes the sidecar's name. A save stopped at any point (a kill, a full disk) leaves the checkpoint on disk,
old or new, with a file holding its own train state, and ``resume_state`` takes whichever of the two is
bound to it.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import torch

from edmcgs.atomic import atomic_output, fsync_folder
from edmcgs.errors import CheckpointError
from edmcgs.model.checkpoint import checkpoint_payload, write_checkpoint

FORMAT = "edmcgs-train-state"
VERSION = 1
SUFFIX = ".train-state"
STAGED = ".new"
"""Suffix of a final save's train state until its checkpoint is in place."""


def sidecar_path(checkpoint: str | os.PathLike) -> Path:
    """Where a final checkpoint's train state lives: ``NAME.train-state`` beside it."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + SUFFIX)


def _staged_path(checkpoint: str | os.PathLike) -> Path:
    path = sidecar_path(checkpoint)
    return path.with_name(path.name + STAGED)


def write_sidecar(checkpoint: str | os.PathLike, train_state: dict, checkpoint_checksum: str, *,
                  staged: bool = False) -> Path:
    """Write ``train_state`` beside ``checkpoint`` (atomically), bound to the checkpoint's checksum;
    ``staged``: under the name a final save writes it before its checkpoint (``save_final``)."""
    path = _staged_path(checkpoint) if staged else sidecar_path(checkpoint)
    payload = {"format": FORMAT, "version": VERSION, "checkpoint": checkpoint_checksum,
               "train_state": train_state}
    with atomic_output(path, CheckpointError) as tmp:
        torch.save(payload, tmp)
    return path


def save_final(model, checkpoint: str | os.PathLike, train_state: dict) -> str:
    """Write a final checkpoint and its train-state sidecar as one unit (see the module docstring);
    returns the checkpoint's checksum."""
    checkpoint = Path(checkpoint)
    payload = checkpoint_payload(model)
    before = _identity(checkpoint)
    try:
        staged = write_sidecar(checkpoint, train_state, payload["checksum"], staged=True)
        write_checkpoint(payload, checkpoint)
    except BaseException:
        if _identity(checkpoint) == before:  # the old checkpoint is still there: the new state is no one's
            _staged_path(checkpoint).unlink(missing_ok=True)
        raise
    os.replace(staged, sidecar_path(checkpoint))
    fsync_folder(checkpoint.parent)
    return payload["checksum"]


def _identity(path: Path) -> tuple[int, int] | None:
    """Which file is at ``path`` (a rename puts another one there)."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        return None
    return stat.st_dev, stat.st_ino


def remove_sidecar(checkpoint: str | os.PathLike) -> None:
    """Remove the sidecar beside ``checkpoint`` (and a final save's staged one), if any."""
    sidecar_path(checkpoint).unlink(missing_ok=True)
    _staged_path(checkpoint).unlink(missing_ok=True)


def resume_state(checkpoint: str | os.PathLike, payload: dict) -> tuple[dict | None, str]:
    """The train state to continue from the checkpoint whose validated payload is ``payload``, and a
    phrase saying where it came from (or why there is none). A damaged sidecar, or one that belongs to
    another checkpoint, raises ``CheckpointError`` (removing it resumes with a fresh optimizer)."""
    embedded = payload.get("train_state")
    if embedded is not None:
        return embedded, "its optimizer state"
    path = sidecar_path(checkpoint)
    staged = _staged_path(checkpoint)
    if staged.is_file():  # a final save stopped after its checkpoint's rename: the state is there
        with contextlib.suppress(CheckpointError):  # or before it: the state of a checkpoint never kept
            return _read_sidecar(checkpoint, staged, payload)
    if not path.is_file():
        return None, f"no optimizer state (no {path.name} beside it): a fresh optimizer from step 0"
    return _read_sidecar(checkpoint, path, payload)


def _read_sidecar(checkpoint: str | os.PathLike, path: Path, payload: dict) -> tuple[dict, str]:
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
                              f"a copied or older file); {remedy}")
    state = side.get("train_state")
    step = state.get("step") if isinstance(state, dict) else None
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(f"{path}: train_state.step must be an integer >= 0 ({remedy})")
    return state, f"the optimizer state in {path.name}"
