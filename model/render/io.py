"""What a render takes and gives: boundary validation of the Gaussians and camera, and RenderOutput.

Both rasterizers call ``check_inputs`` so they accept and reject exactly the same things.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics, validate_pose
from edmcgs.model.render.sh import NUM_COEFFS


@dataclass
class RenderOutput:
    """One rendered view (torch tensors from ``rasterize``, numpy arrays from ``rasterize_fast``).

    image: [H, W, C] colour (C = 1 grey or 3 RGB), background composited under the splats
    alpha: [H, W] accumulated opacity 1 - T, or None unless asked for
    depth: [H, W] expected camera z of the blended splats (sum w_i z_i / alpha; 0 where alpha = 0),
           or None unless asked for
    """

    image: Any
    alpha: Any = None
    depth: Any = None


@dataclass
class Checked:
    """Validated inputs: torch tensors of one float dtype on one device (the means'), or, for the
    fast path, float32 numpy arrays."""

    means: Any       # [N, 3]
    quats: Any       # [N, 4]
    scales: Any      # [N, 3]
    opacities: Any   # [N]
    colors: Any      # [N, C] or [N, K, C]
    w2c: Any         # [4, 4] (torch: means' dtype; numpy: float64)
    background: Any  # [C] (torch: means' dtype; numpy: float32)
    channels: int


def _shape_error(name: str, want: str, got) -> InvalidInputError:
    return InvalidInputError(f"{name} must have shape {want}, got {tuple(got)}")


def as_float32_arrays(**named) -> dict:
    """numpy float32 C-contiguous copies (or views) of array-likes and torch tensors, by name."""
    out = {}
    for name, value in named.items():
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        try:
            out[name] = np.ascontiguousarray(value, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"{name} must be an array of numbers") from exc
    return out


def check_inputs(means, quats, scales, opacities, colors, w2c, intrinsics, background, near) -> Checked:
    """Validate everything at the public boundary; raise InvalidInputError naming the argument.

    The five Gaussian arrays are all torch tensors (one floating dtype, one device) or all numpy
    arrays (the fast path converts to float32 first).
    """
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    is_torch = isinstance(means, torch.Tensor)
    kind = torch.Tensor if is_torch else np.ndarray
    for name, value in named.items():
        if not isinstance(value, kind):
            raise InvalidInputError(f"{name} must be a {kind.__module__}.{kind.__name__}, "
                                    f"got {type(value).__name__}")
    if is_torch and not means.is_floating_point():
        raise InvalidInputError(f"means must be a floating-point tensor, got {means.dtype}")
    for name, value in named.items():
        if value.dtype != means.dtype or (is_torch and value.device != means.device):
            where = f"({means.dtype}, {means.device})" if is_torch else f"({means.dtype})"
            got = f"({value.dtype}, {value.device})" if is_torch else f"({value.dtype})"
            raise InvalidInputError(f"{name} must match means' dtype and device {where}, got {got}")
    if means.ndim != 2 or means.shape[1] != 3:
        raise _shape_error("means", "[N, 3]", means.shape)
    n = means.shape[0]
    if quats.shape != (n, 4):
        raise _shape_error("quats", f"[{n}, 4]", quats.shape)
    if scales.shape != (n, 3):
        raise _shape_error("scales", f"[{n}, 3]", scales.shape)
    if opacities.shape != (n,):
        raise _shape_error("opacities", f"[{n}]", opacities.shape)
    if colors.ndim == 2 and colors.shape[0] == n and colors.shape[1] in (1, 3):
        channels = colors.shape[1]
    elif (colors.ndim == 3 and colors.shape[0] == n and colors.shape[1] in NUM_COEFFS
          and colors.shape[2] in (1, 3)):
        channels = colors.shape[2]
    else:
        raise InvalidInputError(f"colors must be [{n}, C] or SH coefficients [{n}, K, C] with C in (1, 3) "
                                f"and K in (1, 4, 9, 16), got {tuple(colors.shape)}")
    if not isinstance(intrinsics, Intrinsics):
        raise InvalidInputError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if isinstance(near, bool) or not isinstance(near, (int, float)) or not math.isfinite(near) or near <= 0:
        raise InvalidInputError(f"near must be a finite number > 0, got {near!r}")

    device_bg = (is_torch and isinstance(background, torch.Tensor) and background.device == means.device
                 and means.device.type != "cpu")
    device_flags = None
    if is_torch and (means.device.type != "cpu" or means.dtype not in (torch.float32, torch.float64)):
        # Every check as one flag on the device, read back at once: one host sync per render, not eight.
        with torch.no_grad():
            flags = [torch.isfinite(value).all() for value in named.values()]
            flags += [(scales >= 0).all(), ((opacities >= 0) & (opacities <= 1)).all(),
                      (quats != 0).any(-1).all()]
            if device_bg:
                flags.append(torch.isfinite(background).all())
            device_flags = torch.stack(flags).tolist()
        for name, finite in zip(named, device_flags, strict=False):
            if not finite:
                raise InvalidInputError(f"{name} contains NaN or Inf")
        problems = ("scales must be >= 0 (linear scales, not log-scales)",
                    "opacities must lie in [0, 1] (activated, not logits)",
                    "quats has a zero quaternion; it describes no rotation")
        for ok, problem in zip(device_flags[len(named):], problems, strict=False):
            if not ok:
                raise InvalidInputError(problem)
    else:
        # float32/64 on the CPU: the same checks, in the same order, compiled (imported here: numba
        # stays off a GPU's path); a contiguous CPU tensor is viewed, not copied
        from edmcgs.model.render.checks_fast import first_problem

        arrays = (v.detach().numpy() if is_torch else v for v in named.values())
        problem = first_problem(*(np.ascontiguousarray(a) for a in arrays))
        if problem is not None:
            raise InvalidInputError(problem)

    w2c64 = validate_pose(w2c, name="w2c")
    if device_bg:  # a background already on the device stays there (its finiteness was read above)
        try:
            bg_out = torch.broadcast_to(background.detach().to(means.dtype), (channels,))
        except RuntimeError as exc:
            raise InvalidInputError(
                f"background must be a number or {channels} numbers, got {tuple(background.shape)}") from exc
        if not device_flags[-1]:
            raise InvalidInputError("background contains NaN or Inf")
        w2c_out = to_device(torch.as_tensor(w2c64, dtype=means.dtype), means.device)
        return Checked(means, quats, scales, opacities, colors, w2c_out, bg_out, channels)
    if background is None:
        bg = np.zeros(channels)
    else:
        if isinstance(background, torch.Tensor):
            background = background.detach().cpu().numpy()
        try:
            bg = np.array(np.broadcast_to(np.asarray(background, dtype=np.float64), (channels,)))
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(
                f"background must be a number or {channels} numbers, got {background!r}") from exc
        if not np.isfinite(bg).all():
            raise InvalidInputError("background contains NaN or Inf")
    if is_torch:
        w2c_out = to_device(torch.as_tensor(w2c64, dtype=means.dtype), means.device)
        bg_out = to_device(torch.as_tensor(bg, dtype=means.dtype), means.device)
    else:
        w2c_out, bg_out = w2c64, bg.astype(np.float32)
    return Checked(means, quats, scales, opacities, colors, w2c_out, bg_out, channels)


def to_device(host, device):
    """A host tensor (or array) on ``device`` without waiting for that device: on a GPU it is pinned and
    copied non_blocking (torch's pinned-block cache keeps it until the copy has run), where a plain copy
    would wait for every queued kernel first. Unchanged on the CPU."""
    host = torch.as_tensor(host)
    device = torch.device(device)
    if device.type != "cuda":
        return host.to(device)
    return host.pin_memory().to(device, non_blocking=True)
