"""What a render takes and gives: boundary validation of the Gaussians and camera, and RenderOutput.

Both rasterizers call ``check_inputs`` so they accept and reject exactly the same things.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from edmcgs.model.camera import Intrinsics, validate_pose
from edmcgs.model.sh import NUM_COEFFS

from edmcgs.errors import InvalidInputError


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
    """Validated inputs as tensors of one float dtype on one device (the means')."""

    means: torch.Tensor      # [N, 3]
    quats: torch.Tensor      # [N, 4]
    scales: torch.Tensor     # [N, 3]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor     # [N, C] or [N, K, C]
    w2c: torch.Tensor        # [4, 4]
    background: torch.Tensor  # [C]
    channels: int


def _shape_error(name: str, want: str, got) -> InvalidInputError:
    return InvalidInputError(f"{name} must have shape {want}, got {tuple(got)}")


def check_inputs(means, quats, scales, opacities, colors, w2c, intrinsics, background, near) -> Checked:
    """Validate everything at the public boundary; raise InvalidInputError naming the argument.

    Tensors must share one floating dtype and device; the rasterizers convert numpy first.
    """
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors}
    for name, value in named.items():
        if not isinstance(value, torch.Tensor):
            raise InvalidInputError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if not means.is_floating_point():
        raise InvalidInputError(f"means must be a floating-point tensor, got {means.dtype}")
    for name, value in named.items():
        if value.dtype != means.dtype or value.device != means.device:
            raise InvalidInputError(f"{name} must match means' dtype and device ({means.dtype}, "
                                    f"{means.device}), got ({value.dtype}, {value.device})")
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

    with torch.no_grad():
        # One host sync for every check, so validation stays cheap on an accelerator too.
        flags = torch.stack([
            *(torch.isfinite(v).all() for v in named.values()),
            (scales >= 0).all(),
            ((opacities >= 0) & (opacities <= 1)).all(),
            (quats.abs().amax(-1) > 0).all(),
        ]).tolist() if n else [True] * 8
    for ok, name in zip(flags[:5], named, strict=True):
        if not ok:
            raise InvalidInputError(f"{name} contains NaN or Inf")
    if not flags[5]:
        raise InvalidInputError("scales must be >= 0 (linear scales, not log-scales)")
    if not flags[6]:
        raise InvalidInputError("opacities must lie in [0, 1] (activated, not logits)")
    if not flags[7]:
        raise InvalidInputError("quats has a zero quaternion; it describes no rotation")

    w2c_t = torch.as_tensor(validate_pose(w2c, name="w2c"), dtype=means.dtype, device=means.device)
    if background is None:
        bg = torch.zeros(channels, dtype=means.dtype, device=means.device)
    else:
        if isinstance(background, torch.Tensor):
            background = background.detach().cpu().numpy()
        try:
            bg_np = np.broadcast_to(np.asarray(background, dtype=np.float64), (channels,))
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(
                f"background must be a number or {channels} numbers, got {background!r}") from exc
        if not np.isfinite(bg_np).all():
            raise InvalidInputError("background contains NaN or Inf")
        bg = torch.as_tensor(np.array(bg_np), dtype=means.dtype, device=means.device)
    return Checked(means, quats, scales, opacities, colors, w2c_t, bg, channels)
