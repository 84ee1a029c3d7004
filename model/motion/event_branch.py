"""The event-driven Markov transition: event map -> Phi -> local motion codes -> g_phi displacement.

Exact zero for an empty window is structural, not learned: Phi has no biases (Phi(0) = 0, so every
motion code of an all-zero map is 0) and the transition is g(gamma(mu), m) - g(gamma(mu), 0), which
vanishes whenever m = 0 however g was trained. ``EdMCGS`` also skips the branch for an all-zero map.
With local sampling, a control point whose neighbourhood (Phi's receptive field, ``FIELD`` x ``pool``
event-camera pixels) saw no event gets an exactly zero displacement too.
"""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from edmcgs.model.motion.encoding import encoded_size, positional_encoding
from edmcgs.model.motion.point_terms import PointTerms

FEATURES = 32
"""Channels of Phi's output (the motion code's width)."""
FIELD = 7 + 4 * 2 + 2 * 4
"""Phi's receptive field in pixels of the map it reads (23)."""


def saturate(log_change: Tensor, limit: float) -> Tensor:
    """Clamp a predicted log-luminance change C * I_E to [-limit, limit].

    A pixel whose intensity stays in [0, 1] cannot change its log(I + eps) by more than
    log(1 + 1/eps), so counts beyond that are noise or a burst: clamping keeps every motion code, and so
    the displacement, bounded whatever the event count, and is the identity on physical windows.
    Zero stays exactly zero.
    """
    return log_change.clamp(-limit, limit)


class EventEncoder(nn.Module):
    """Phi: Conv(1->16, k7, s2) act Conv(16->32, k5, s2) act Conv(32->32, k3, s1), bias-free
    (act: ReLU, or LeakyReLU 0.1 with ``act="leaky"``).

    A 32-channel map at a quarter of the input resolution, receptive field ``FIELD`` = 23 px.
    The input is saturated first (``saturate``), so the output is bounded in the event count; with
    ``pool`` > 1 it is then averaged over pool x pool blocks (a field of 23 x pool pixels, no new weights).
    """

    def __init__(self, *, limit: float, pool: int = 1, act: str = "relu"):
        super().__init__()
        self.limit = float(limit)
        self.pool = int(pool)
        self.act = act
        self.dead: Tensor | None = None
        """Fraction of the second layer's channels never above 0 on the last map with gradients on (a
        training-health scalar tensor, left on the map's device: reading it is the caller's sync)."""
        self.conv1 = nn.Conv2d(1, 16, 7, stride=2, padding=3, bias=False)
        self.conv2 = nn.Conv2d(16, 32, 5, stride=2, padding=2, bias=False)
        self.conv3 = nn.Conv2d(32, FEATURES, 3, stride=1, padding=1, bias=False)

    def forward(self, event_map: Tensor) -> Tensor:
        """event_map: Tensor  # [B, 1, H, W] float32 (C times the signed polarity sum)
        returns Tensor  # [B, 32, ceil(H/4), ceil(W/4)]
        """
        x = saturate(event_map, self.limit)
        if self.pool > 1:  # a pool-times wider receptive field; the mean keeps zero and the bound
            x = F.avg_pool2d(x, self.pool, ceil_mode=True)
        h = self._act(self.conv1(x))
        h = self.conv2(h)
        if torch.is_grad_enabled():  # a training statistic: inference skips its reduction
            with torch.no_grad():
                self.dead = (h.amax(dim=(0, 2, 3)) <= 0).float().mean()
        return self.conv3(self._act(h))

    @property
    def dead_fraction(self) -> float:
        """``dead`` as a number (NaN before the first map with gradients on)."""
        return float("nan") if self.dead is None else float(self.dead)

    def _act(self, x: Tensor) -> Tensor:
        # Both fix 0: a bias-free Phi maps an empty window to exactly 0 either way.
        return F.leaky_relu(x, 0.1) if self.act == "leaky" else torch.relu(x)


def sample_local(features: Tensor, uv: Tensor, valid: Tensor, width: int, height: int) -> Tensor:
    """Bilinear read of ``features`` at pixel positions (the local motion codes m_j).

    features: Tensor  # [32, h, w] Phi's map of a [height, width] event map
    uv: Tensor        # [M, 2] pixel coordinates on the event camera, pixel centres at integers
    valid: Tensor     # [M] bool, False for points behind the camera (their code is 0)
    returns Tensor    # [M, 32]; zero outside the image
    """
    # align_corners=False puts the image's outer edge at -1 / +1, i.e. pixel centre i at (2i + 1)/W - 1,
    # independent of the map's resolution, so the quarter-resolution map is read at the right place.
    gx = (2.0 * uv[:, 0] + 1.0) / width - 1.0
    gy = (2.0 * uv[:, 1] + 1.0) / height - 1.0
    grid = torch.stack([gx, gy], -1)
    grid = torch.where(valid[:, None] & torch.isfinite(grid), grid, torch.full_like(grid, 4.0))
    out = F.grid_sample(features[None], grid[None, None], mode="bilinear", padding_mode="zeros",
                        align_corners=False)
    return out[0, :, 0].T


def sample_global(features: Tensor, m: int) -> Tensor:
    """The ``local_sampling=False`` ablation: one average-pooled code shared by all ``m`` points."""
    return features.mean(dim=(1, 2))[None].expand(m, -1)


class EventTransition(nn.Module):
    """g_phi(gamma(mu_j), m_j): Linear -> 64, ReLU, Linear -> 3 (last layer zero-initialised)."""

    def __init__(self, *, pos_freqs: int, hidden: int):
        super().__init__()
        self.pos_freqs = pos_freqs
        self.hidden = nn.Linear(encoded_size(3, pos_freqs) + FEATURES, hidden)
        self.out = nn.Linear(hidden, 3)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self._points = PointTerms()

    def forward(self, x: Tensor, codes: Tensor) -> Tensor:
        """x: Tensor      # [M, 3] canonical control points, normalised scene coordinates
        codes: Tensor  # [M, 32] motion codes
        returns Tensor # [M, 3] displacement in scene extents; exactly 0 where codes == 0
        """
        x_term, g_zero = self._points.get(self, x, self._x_terms)
        w = self.hidden.weight
        g = self.out(torch.relu(torch.addmm(x_term, codes, w[:, w.shape[1] - codes.shape[1]:].T)))
        # Two GEMMs need not round identically row for row; the mask makes the zero exact.
        return (g - g_zero) * (codes != 0).any(-1, keepdim=True)

    def _x_terms(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The hidden layer's gamma(x) part with its bias [M, hidden], and g(gamma(x), 0) [M, 3]: the
        transition is g(gamma(x), m) - g(gamma(x), 0) and only m changes between calls."""
        enc = positional_encoding(x, self.pos_freqs)
        x_term = torch.addmm(self.hidden.bias, enc, self.hidden.weight[:, :enc.shape[1]].T)
        return x_term, self.out(torch.relu(x_term))
