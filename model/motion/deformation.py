"""The RGB prior f_theta(gamma(sg(mu_j)), gamma(t)): a deformation MLP evaluated at the control points."""

from collections.abc import Callable

import torch
from torch import Tensor, nn

from edmcgs.model.motion.encoding import encoded_size, positional_encoding
from edmcgs.model.motion.point_terms import PointTerms
from edmcgs.model.render.io import to_device


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
        self._points = PointTerms()
        self.compiled_field: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None
        """torch.compile's ``field``, which training calls in its place (``Trainer(compile=True)``)."""

    def forward(self, x: Tensor, t: float | Tensor) -> tuple[Tensor, Tensor]:
        """x: Tensor  # [M, 3] control points in normalised scene coordinates (about [-1, 1]), no grad
        t: normalised time in [0, 1] (a Python float or a float64 scalar: it is encoded in float64)
        returns (translation [M, 3] in scene extents, rotation delta [M, 4] to add to the identity)
        """
        t_enc = self.encode_time(t, x)                                                  # [1, Dt]
        if torch.is_grad_enabled():
            return (self.compiled_field or self.field)(x, t_enc)
        # The layers that read the input [gamma(x), gamma(t)] split it by columns: the gamma(x) part (with
        # the bias) is time-independent and kept between inference calls, the gamma(t) part is one row.
        return self._trunk(self._points.get(self, x, self._x_terms), t_enc)

    def field(self, x: Tensor, t_enc: Tensor) -> tuple[Tensor, Tensor]:
        """``forward`` of the encoded time ``t_enc`` [1, Dt], nothing kept: one pure function of tensors."""
        return self._trunk(self._x_terms(x), t_enc)

    def _trunk(self, x_terms: dict[int, Tensor], t_enc: Tensor) -> tuple[Tensor, Tensor]:
        dt = t_enc.shape[1]
        h = None
        for i, layer in enumerate(self.layers):
            if i in x_terms:
                w = layer.weight
                pre = x_terms[i] + t_enc @ w[:, w.shape[1] - dt:].T
                h = pre if h is None else torch.addmm(pre, h, w[:, :h.shape[1]].T)
            else:
                h = layer(h)
            h = torch.relu(h)
        return self.translation(h), self.rotation(h)

    def encode_time(self, t: float | Tensor, like: Tensor) -> Tensor:
        """gamma(t) [1, Dt] in ``like``'s dtype and device, computed in float64 and then cast: sin(2^k pi t)
        of a float32 t would lose microseconds of a long span. A number is encoded on the host and sent
        as one row (on a GPU a dozen launches fewer, and no wait for the device)."""
        t64 = torch.as_tensor(t, dtype=torch.float64).reshape(1, 1)
        return to_device(positional_encoding(t64, self.time_freqs).to(like.dtype), like.device)

    def _x_terms(self, x: Tensor) -> dict[int, Tensor]:
        """gamma(x) times the gamma(x) columns of each layer that reads the input, plus its bias, by
        layer index: [M, width] each."""
        enc = positional_encoding(x, self.pos_freqs)
        terms = {}
        for i in (0, self.skip) if self.skip > 0 else (0,):
            w = self.layers[i].weight
            start = 0 if i == 0 else w.shape[0]  # the skip layer reads [h, gamma(x), gamma(t)]
            terms[i] = torch.addmm(self.layers[i].bias, enc, w[:, start:start + enc.shape[1]].T)
        return terms
