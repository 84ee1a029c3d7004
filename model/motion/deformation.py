"""The RGB prior f_theta(gamma(sg(mu_j)), gamma(t)): a deformation MLP evaluated at the control points."""

import torch
from torch import Tensor, nn

from edmcgs.model.motion.encoding import encoded_size, positional_encoding


class DeformationField(nn.Module):
    """Per-control-point translation and rotation delta as a function of position and time.

    The trunk follows Deformable 3DGS (ReLU MLP with the input re-injected half-way); the two heads are
    zero-initialised so that training starts from the identity deformation.
    """

    def __init__(self, *, width: int, depth: int, pos_freqs: int, time_freqs: int):
        super().__init__()
        self.pos_freqs, self.time_freqs = pos_freqs, time_freqs
        in_dim = encoded_size(3, pos_freqs) + encoded_size(1, time_freqs)
        self.skip = depth // 2
        layers = []
        for i in range(depth):
            fan_in = in_dim if i == 0 else width + (in_dim if i == self.skip else 0)
            layers.append(nn.Linear(fan_in, width))
        self.layers = nn.ModuleList(layers)
        self.translation = nn.Linear(width, 3)
        self.rotation = nn.Linear(width, 4)
        for head in (self.translation, self.rotation):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, x: Tensor, t: float | Tensor) -> tuple[Tensor, Tensor]:
        """x: Tensor  # [M, 3] control points in normalised scene coordinates (about [-1, 1]), no grad
        t: normalised time in [0, 1] (a Python float or a float64 scalar: it is encoded in float64)
        returns (translation [M, 3] in scene extents, rotation delta [M, 4] to add to the identity)
        """
        # gamma(t) in float64, then cast: sin(2^k pi t) of a float32 t would lose microseconds of a long span.
        t64 = torch.as_tensor(t, dtype=torch.float64, device=x.device).reshape(1, 1)
        t_enc = positional_encoding(t64, self.time_freqs).to(x.dtype).expand(x.shape[0], -1)
        inp = torch.cat([positional_encoding(x, self.pos_freqs), t_enc], -1)
        h = inp
        for i, layer in enumerate(self.layers):
            if i == self.skip and i > 0:
                h = torch.cat([h, inp], -1)
            h = torch.relu(layer(h))
        return self.translation(h), self.rotation(h)
