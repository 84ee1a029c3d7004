"""The canonical 3D Gaussians (learnable state) and a deformed snapshot of them (``GaussianState``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from edmcgs.model.motion.row_grad import gather_rows
from edmcgs.model.render.sh import SH_C0


@dataclass
class GaussianState:
    """The Gaussians at one time, ready to rasterize (activated, world frame).

    means: Tensor      # [N, 3] float32
    quats: Tensor      # [N, 4] float32 (w, x, y, z), unit
    scales: Tensor     # [N, 3] float32, linear, > 0
    opacities: Tensor  # [N] float32 in (0, 1)
    colors: Tensor     # [N, C] float32 in (0, 1), or SH coefficients [N, K, C] with K = (deg + 1)^2
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def tensors(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(means, quats, scales, opacities, colors): the rasterizers' argument order."""
        return self.means, self.quats, self.scales, self.opacities, self.colors

    def detach(self) -> GaussianState:
        return GaussianState(*(t.detach() for t in self.tensors()))


PER_GAUSSIAN = ("means", "quats", "log_scales", "opacity_logits", "features")
"""Names of the per-Gaussian parameters (first dimension N), in optimizer-group order."""
STATIC = -1
"""The ``birth`` of a Gaussian of the static set (config.static_set): drawn in every window, never moved."""


class Gaussians(nn.Module):
    """Canonical Gaussians: means, quaternions, log-scales, opacity logits and colour features.

    ``features`` is [N, K, C]: with K = 1 (sh_degree 0) it holds colour logits (colour = sigmoid),
    otherwise SH coefficients for the rasterizer.
    """

    def __init__(self, means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor,
                 features: Tensor, birth: Tensor | None = None):
        super().__init__()
        self.means = nn.Parameter(means)
        self.quats = nn.Parameter(quats)
        self.log_scales = nn.Parameter(log_scales)
        self.opacity_logits = nn.Parameter(opacity_logits)
        self.features = nn.Parameter(features)
        # [N] int64 anchor index whose gap this Gaussian lives in (config.anchor_windows; STATIC: the
        # static set, in every gap and never moved), or None: every Gaussian at every time. A buffer:
        # densification copies it, the optimizer never sees it.
        self.register_buffer("birth", None if birth is None else birth.long())

    @classmethod
    def empty(cls, n: int, sh_degree: int, channels: int, *, birth: bool = False) -> Gaussians:
        """Zero-filled placeholders of the right shapes (a checkpoint's tensors are loaded into them)."""
        k = (sh_degree + 1) ** 2
        return cls(torch.zeros(n, 3), torch.zeros(n, 4), torch.zeros(n, 3), torch.zeros(n),
                   torch.zeros(n, k, channels), torch.zeros(n, dtype=torch.long) if birth else None)

    @classmethod
    def from_points(cls, points: Tensor, colors: Tensor, scales: Tensor, *, sh_degree: int,
                    opacity: float = 0.1, birth: Tensor | None = None) -> Gaussians:
        """Isotropic Gaussians at ``points``.

        points: Tensor  # [N, 3]
        colors: Tensor  # [N, C] in [0, 1]
        scales: Tensor  # [N] initial isotropic scale, > 0
        """
        n, c = colors.shape
        k = (sh_degree + 1) ** 2
        features = torch.zeros(n, k, c)
        col = colors.clamp(0.02, 0.98)
        features[:, 0] = torch.logit(col) if k == 1 else (col - 0.5) / SH_C0
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        log_scales = torch.log(scales.clamp_min(1e-7))[:, None].repeat(1, 3)
        opacity_logits = torch.full((n,), float(torch.logit(torch.tensor(opacity))))
        return cls(points.float().clone(), quats, log_scales, opacity_logits, features, birth)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return round(self.features.shape[1] ** 0.5) - 1

    @property
    def channels(self) -> int:
        return int(self.features.shape[2])

    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    def colors(self) -> Tensor:
        """[N, C] colours in (0, 1) for degree 0, else the SH coefficients [N, K, C]."""
        if self.features.shape[1] == 1:
            return torch.sigmoid(self.features[:, 0])
        return self.features

    def activated(self, rows: Tensor | None = None) -> list[Tensor]:
        """[means, quats, scales, opacities, colors] of the Gaussians ``rows`` (all when None), each as
        ``scales()``, ``opacities()``, ``colors()`` give it (quats as stored): the work follows the rows."""
        if rows is None:
            return [self.means, self.quats, self.scales(), self.opacities(), self.colors()]
        features = gather_rows(self.features, rows)  # sparse gradients: the rows' work, not N's
        colors = torch.sigmoid(features[:, 0]) if features.shape[1] == 1 else features
        return [gather_rows(self.means, rows), gather_rows(self.quats, rows),
                torch.exp(gather_rows(self.log_scales, rows)),
                torch.sigmoid(gather_rows(self.opacity_logits, rows)), colors]

    def replace(self, tensors: dict[str, Tensor]) -> None:
        """Swap in new per-Gaussian parameters (after densification); N may change."""
        for name in PER_GAUSSIAN:
            setattr(self, name, nn.Parameter(tensors[name]))
        if self.birth is not None:
            self.birth = tensors["birth"].long()

    def visible_in(self, window: int | None) -> Tensor | None:
        """[N] float 0/1: the Gaussians that live in anchor ``window``'s gap (and the static set's);
        None: all (no windows)."""
        if self.birth is None or window is None:
            return None
        return ((self.birth == int(window)) | (self.birth == STATIC)).to(self.means.dtype)

    def static(self) -> Tensor | None:
        """[N] bool: the static set (never moved); None when there is none."""
        if self.birth is None:
            return None
        mask = self.birth == STATIC
        return mask if bool(mask.any()) else None
