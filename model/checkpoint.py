"""EdMCGS checkpoints: one torch file of plain containers and tensors, loaded with ``weights_only=True``.

Schema (version 3)::

    {"format": "edmcgs-checkpoint", "version": 3,
     "meta": {t_start_us, t_end_us, anchors_us [F] int64, intrinsics {fx, fy, cx, cy, width, height},
              event_width, event_height, trajectory {t_us [T] int64, c2w [T,4,4] float64} | None,
              channels, config {...}, has_event_branch,
              frozen [M] bool | None, freeze_threshold float, lean {...}},   # version 2
     "sizes": {num_gaussians, num_control_points},
     "state_dict": {name: tensor},   # version 3: online_transition.* when distilled
     "train_state": {...} | None}   # optimizer and progress, only in checkpoints written mid-training
                                    # (a final one: in the sidecar NAME.train-state, model/train/resume.py)

Version 2 adds what the scene leaves out (``edmcgs.model.motion.leanness``): the frozen control points
(decided when a final checkpoint is written, ``train_state`` None) and ``lean``, the record of every
decision; a static camera's trajectory is stored as one pose. Version 1 files load with nothing frozen
and ``lean`` derived from the weights. Version 3 adds the optional ``online_transition`` (the event
transition online anchors use past the span, ``model/online/distill.py``); versions 1 and 2 have none. A
missing, truncated, foreign or newer file raises ``CheckpointError``.
Writes are atomic (a temporary file in the same folder, fsynced, then renamed over the target).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import re
from pathlib import Path

import numpy as np
import torch

from edmcgs.atomic import atomic_output
from edmcgs.errors import CheckpointError, EdmcgsError, translated
from edmcgs.filekind import check_checkpoint
from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.model.config import EdmcgsConfig
from edmcgs.model.dynamic import EdMCGS, SceneMeta
from edmcgs.model.motion.background import BackgroundLayer
from edmcgs.model.motion.control_points import ControlPoints
from edmcgs.model.motion.event_branch import EventTransition
from edmcgs.model.motion.gaussians import STATIC, Gaussians
from edmcgs.model.motion.leanness import decisions, frozen_control_points

FORMAT = "edmcgs-checkpoint"
VERSION = 3


def save_checkpoint(model: EdMCGS, path: str | os.PathLike, *, train_state: dict | None = None,
                    freeze_threshold: float | None = None) -> str:
    """Write ``model`` (and optionally the trainer's resumable state) to ``path`` atomically; returns the
    file's checksum (a sidecar of train state names the checkpoint it belongs to by it).

    A final checkpoint (no ``train_state``) records the frozen control points: those whose prior motion
    stays below ``freeze_threshold`` (world units; default ``leanness.FREEZE_FRACTION`` of the extent;
    0 freezes only points that do not move at all). ``model`` itself is left as it was.
    """
    payload = checkpoint_payload(model, train_state=train_state, freeze_threshold=freeze_threshold)
    write_checkpoint(payload, path)
    return payload["checksum"]


def checkpoint_payload(model: EdMCGS, *, train_state: dict | None = None,
                       freeze_threshold: float | None = None) -> dict:
    """What ``save_checkpoint`` writes, its ``checksum`` included (known before the file is written:
    a final checkpoint's train-state sidecar is written first, ``model/train/resume.py``)."""
    meta = model.meta
    if train_state is None:
        frozen, threshold = frozen_control_points(model, freeze_threshold)
    else:  # mid-training: the motion is still changing
        frozen, threshold = None, 0.0
    trajectory = meta.trajectory
    static = trajectory is not None and trajectory.is_static
    if static and len(trajectory.t_us) > 1:
        trajectory = Trajectory(trajectory.t_us[:1], trajectory.c2w[:1])  # one pose: no interpolation
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "meta": {
            "t_start_us": int(meta.t_start_us),
            "t_end_us": int(meta.t_end_us),
            "anchors_us": torch.from_numpy(np.asarray(meta.anchors_us, dtype=np.int64).copy()),
            "intrinsics": {"fx": float(meta.intrinsics.fx), "fy": float(meta.intrinsics.fy),
                           "cx": float(meta.intrinsics.cx), "cy": float(meta.intrinsics.cy),
                           "width": int(meta.intrinsics.width), "height": int(meta.intrinsics.height)},
            "event_width": int(meta.event_width),
            "event_height": int(meta.event_height),
            "trajectory": None if trajectory is None else {
                "t_us": torch.from_numpy(np.asarray(trajectory.t_us, dtype=np.int64).copy()),
                "c2w": torch.from_numpy(np.asarray(trajectory.c2w, dtype=np.float64).copy())},
            "channels": int(meta.channels),
            "config": model.config.to_dict(),
            "has_event_branch": bool(meta.has_event_branch),
            "frozen": None if frozen is None else torch.from_numpy(np.asarray(frozen, dtype=bool).copy()),
            "freeze_threshold": float(threshold),
            "lean": decisions(model, frozen, threshold, static),
        },
        "sizes": {"num_gaussians": len(model.gaussians), "num_control_points": model.control.num_points},
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "train_state": train_state,
    }
    payload["checksum"] = checksum(payload)
    return payload


def write_checkpoint(payload: dict, path: str | os.PathLike) -> None:
    """Write a ``checkpoint_payload`` to ``path`` atomically (its folder created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path, CheckpointError) as tmp:
        torch.save(payload, tmp)


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The validated raw payload (tensors on the CPU); ``CheckpointError`` for anything but ours."""
    path = check_checkpoint(path)  # missing, a recording, not a torch file: said before torch reads it
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's message advises re-running with weights_only=False, i.e. executing the file's code:
        # never repeat that advice. Name the offending global (first line of torch's message) only.
        raise CheckpointError(f"checkpoint {str(path)!r} refers to code or objects an EdMCGS checkpoint "
                              f"never contains ({_unsafe_reason(exc)}); it was not loaded. Use a checkpoint "
                              "written by edmcgs train") from None
    except Exception as exc:  # torch raises RuntimeError, EOFError, zipfile errors ...
        raise CheckpointError(f"checkpoint {str(path)!r} is truncated or not a torch file: "
                              f"{_first_line(exc)}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{str(path)!r} is not an EdMCGS checkpoint (no format {FORMAT!r})")
    version = payload.get("version")
    if not isinstance(version, int) or version < 1:
        raise CheckpointError(f"{str(path)!r}: bad schema version {version!r}")
    if version > VERSION:
        raise CheckpointError(f"{str(path)!r} has schema version {version}, newer than this edmcgs reads "
                              f"({VERSION}); upgrade edmcgs")
    for key in ("meta", "sizes", "state_dict"):
        if not isinstance(payload.get(key), dict):
            raise CheckpointError(f"{str(path)!r}: missing section {key!r}")
    stored = payload.get("checksum")
    if stored is not None:  # files written before checksums have none
        if not isinstance(stored, str) or stored != checksum(payload):
            raise CheckpointError(f"{str(path)!r} is damaged: its checksum does not match its contents "
                                  "(a flipped bit, a partial copy); use another copy")
    try:
        validate(payload)
    except CheckpointError as exc:
        raise CheckpointError(f"{str(path)!r}: {exc}") from None
    return payload


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message, without torch's advice about ``weights_only``."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    lines = [ln for ln in lines if "weights_only" not in ln and "pickle" not in ln.lower()[:12]]
    first = lines[0] if lines else type(exc).__name__
    return first.split(". ")[0][:200]


def _unsafe_reason(exc: BaseException) -> str:
    found = re.search(r"(?:Unsupported global|GLOBAL|global):? *([\w.]+)", str(exc))
    return f"global {found.group(1)}" if found else "an unsupported pickle instruction"


MAX_CAMERA_SIDE = 16_384
"""Largest camera or event-map side a checkpoint may state (px): a corrupt size must not allocate."""
MAX_CAMERA_PIXELS = 64 * 2**20
MAX_GAUSSIANS = 50_000_000
MAX_CONTROL_POINTS = 1_000_000
INDEX_TENSORS = ("control.graph", "control.bind")
"""Integer tensors that index the control points: every value in [0, num_control_points)."""


def checksum(payload: dict) -> str:
    """SHA-256 over meta, sizes and state_dict (tensors by dtype, shape and bytes; the rest by repr)."""
    h = hashlib.sha256()

    def walk(obj) -> None:
        if isinstance(obj, torch.Tensor):
            t = obj.detach().cpu().contiguous()
            h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        elif isinstance(obj, dict):
            h.update(b"{")
            for key in sorted(obj, key=repr):
                h.update(repr(key).encode())
                walk(obj[key])
            h.update(b"}")
        elif isinstance(obj, list | tuple):
            h.update(b"[")
            for item in obj:
                walk(item)
            h.update(b"]")
        else:
            h.update(repr(obj).encode())

    walk({k: payload.get(k) for k in ("meta", "sizes", "state_dict")})
    return h.hexdigest()


def _int(value, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise CheckpointError(f"{name} must be an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise CheckpointError(f"{name}={value} is outside [{lo}, {hi}]")
    return value


def _float(value, name: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise CheckpointError(f"{name} must be a finite number, got {value!r}"[:200])
    if positive and value <= 0:
        raise CheckpointError(f"{name} must be > 0, got {value!r}")
    return float(value)


def _times(value, name: str, *, min_len: int = 1) -> np.ndarray:
    if not isinstance(value, torch.Tensor) or value.dtype != torch.int64 or value.dim() != 1:
        got = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
        raise CheckpointError(f"{name} must be a 1-D int64 tensor, got {got}")
    if value.numel() < min_len:
        raise CheckpointError(f"{name} is empty")
    t = value.numpy()
    if len(t) > 1 and not bool(np.all(np.diff(t) > 0)):
        raise CheckpointError(f"{name} is not strictly increasing")
    return t


def validate(payload: dict) -> None:
    """Check every field of a checkpoint's payload (types, shapes, ranges, index bounds, camera size caps,
    time order) before anything is built from it; CheckpointError in one line naming the field."""
    m, sizes, state = payload["meta"], payload["sizes"], payload["state_dict"]
    for key in ("t_start_us", "t_end_us", "anchors_us", "intrinsics", "event_width", "event_height",
                "trajectory", "channels", "config", "has_event_branch"):
        if key not in m:
            raise CheckpointError(f"meta.{key} is missing")
    t0 = _int(m["t_start_us"], "meta.t_start_us", -(2**62), 2**62)
    t1 = _int(m["t_end_us"], "meta.t_end_us", -(2**62), 2**62)
    if t1 <= t0:
        raise CheckpointError(f"meta.t_end_us ({t1}) is not after meta.t_start_us ({t0})")
    anchors = _times(m["anchors_us"], "meta.anchors_us")
    if anchors[0] < t0 or anchors[-1] > t1:
        raise CheckpointError(f"meta.anchors_us [{anchors[0]}, {anchors[-1]}] leave the span [{t0}, {t1}]")
    intr = m["intrinsics"]
    if not isinstance(intr, dict):
        raise CheckpointError("meta.intrinsics must be a map")
    for key in ("fx", "fy", "cx", "cy"):
        _float(intr.get(key), f"meta.intrinsics.{key}", positive=key in ("fx", "fy"))
    for prefix, w_key, h_key, src in (("meta.intrinsics.", "width", "height", intr),
                                      ("meta.", "event_width", "event_height", m)):
        w = _int(src.get(w_key), prefix + w_key, 1, MAX_CAMERA_SIDE)
        h = _int(src.get(h_key), prefix + h_key, 1, MAX_CAMERA_SIDE)
        if w * h > MAX_CAMERA_PIXELS:
            raise CheckpointError(f"{prefix}{w_key}x{h_key} = {w}x{h} exceeds {MAX_CAMERA_PIXELS} pixels")
    traj = m["trajectory"]
    if traj is not None:
        if not isinstance(traj, dict):
            raise CheckpointError("meta.trajectory must be a map or None")
        tt = _times(traj.get("t_us"), "meta.trajectory.t_us")
        c2w = traj.get("c2w")
        if (not isinstance(c2w, torch.Tensor) or not c2w.is_floating_point()
                or tuple(c2w.shape) != (len(tt), 4, 4)):
            raise CheckpointError(f"meta.trajectory.c2w must be a float tensor [{len(tt)}, 4, 4]")
        if not bool(torch.isfinite(c2w).all()):
            raise CheckpointError("meta.trajectory.c2w contains NaN or Inf")
    _int(m["channels"], "meta.channels", 1, 3)
    if m["channels"] == 2:
        raise CheckpointError("meta.channels must be 1 or 3")
    if not isinstance(m["has_event_branch"], bool):
        raise CheckpointError("meta.has_event_branch must be true or false")
    if not isinstance(m["config"], dict):
        raise CheckpointError("meta.config must be a map")
    n = _int(sizes.get("num_gaussians"), "sizes.num_gaussians", 1, MAX_GAUSSIANS)
    mcp = _int(sizes.get("num_control_points"), "sizes.num_control_points", 1, MAX_CONTROL_POINTS)
    del n
    for key in INDEX_TENSORS:
        value = state.get(key)
        if isinstance(value, torch.Tensor):
            if value.is_floating_point() or value.dtype == torch.bool:
                raise CheckpointError(f"state_dict[{key!r}] must be an integer tensor")
            if value.numel() and (int(value.min()) < 0 or int(value.max()) >= mcp):
                raise CheckpointError(f"state_dict[{key!r}] indexes outside [0, {mcp}) control points")
    for key in ("gaussians.birth", "control.birth"):  # anchor windows: each names an anchor (or STATIC)
        value = state.get(key)
        if isinstance(value, torch.Tensor):
            if value.is_floating_point() or value.dtype == torch.bool:
                raise CheckpointError(f"state_dict[{key!r}] must be an integer tensor")
            if value.numel() and (int(value.min()) < STATIC or int(value.max()) >= len(anchors)):
                raise CheckpointError(f"state_dict[{key!r}] names anchors outside [0, {len(anchors)}) "
                                      f"(or {STATIC}: the static set)")
    train_state = payload.get("train_state")
    if train_state is not None:
        if not isinstance(train_state, dict):
            raise CheckpointError("train_state must be a map or None")
        _int(train_state.get("step"), "train_state.step", 0, 2**40)


def load_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu") -> EdMCGS:
    """The model stored at ``path`` on ``device``, in eval mode."""
    payload = read_checkpoint(path)
    with translated((EdmcgsError, KeyError, TypeError, ValueError, RuntimeError),
                    lambda exc: CheckpointError(f"{str(path)!r} is inconsistent: {exc}"),
                    keep=CheckpointError):
        model = _build(payload)
    return model.to(device).eval()


def _build(payload: dict) -> EdMCGS:
    m = payload["meta"]
    config = EdmcgsConfig.from_dict(m["config"])
    traj = m["trajectory"]
    intr = m["intrinsics"]
    meta = SceneMeta(
        t_start_us=int(m["t_start_us"]), t_end_us=int(m["t_end_us"]),
        anchors_us=m["anchors_us"].numpy().astype(np.int64),
        intrinsics=Intrinsics(float(intr["fx"]), float(intr["fy"]), float(intr["cx"]), float(intr["cy"]),
                              int(intr["width"]), int(intr["height"])),
        event_width=int(m["event_width"]), event_height=int(m["event_height"]),
        trajectory=None if traj is None else Trajectory(traj["t_us"].numpy().astype(np.int64),
                                                         traj["c2w"].numpy().astype(np.float64)),
        channels=int(m["channels"]), config=config.to_dict(), has_event_branch=bool(m["has_event_branch"]))
    frozen = m.get("frozen")  # version 1: absent, nothing frozen
    if frozen is not None:
        frozen = frozen.numpy().astype(bool)
        if frozen.shape != (int(payload["sizes"]["num_control_points"]),):
            raise CheckpointError(f"meta.frozen has shape {frozen.shape}, not [num_control_points]")
    meta.frozen, meta.freeze_threshold = frozen, float(m.get("freeze_threshold", 0.0))
    meta.lean = m.get("lean") or {"sh_degree": {"value": config.sh_degree, "why": "from the weights "
                                                "(a version 1 checkpoint records no decision)"}}
    if meta.has_event_branch != config.has_event_branch:
        raise CheckpointError("has_event_branch disagrees with the config's switches")
    sizes = payload["sizes"]
    n, mcp = int(sizes["num_gaussians"]), int(sizes["num_control_points"])
    state = payload["state_dict"]
    layer = None
    texture = state.get("bg_layer.texture")
    if config.bg_layer:
        if not isinstance(texture, torch.Tensor) or texture.ndim != 3:
            raise CheckpointError("config.bg_layer is on but the state_dict has no [C, H, W] "
                                  "bg_layer.texture")
        layer = BackgroundLayer.empty(*texture.shape)
    gaussians = Gaussians.empty(n, config.sh_degree, meta.channels, birth=config.anchor_windows)
    model = EdMCGS(meta, config, gaussians,
                   ControlPoints.empty(mcp, n, config.skin_k, config.graph_k, birth=config.anchor_windows),
                   torch.zeros(3), 1.0, layer)
    if any(key.startswith("online_transition.") for key in state):
        if not config.has_event_branch:
            raise CheckpointError("the state_dict has an online_transition but the config no event branch")
        model.online_transition = EventTransition(pos_freqs=config.event_pos_freqs,
                                                  hidden=config.event_hidden)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f"state_dict mismatch: missing {missing[:5]}, unexpected {unexpected[:5]}")
    for key, value in state.items():
        if not isinstance(value, torch.Tensor) or value.shape != expected[key].shape:
            raise CheckpointError(f"state_dict[{key!r}] has the wrong shape")
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise CheckpointError(f"state_dict[{key!r}] contains NaN or Inf")
    model.load_state_dict(state)
    return model
