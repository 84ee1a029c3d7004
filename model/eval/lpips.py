"""LPIPS (VGG, v0.1) of Zhang et al. 2018, on weights the user already has on disk (never downloaded).

    d(x, y) = sum_l mean_hw( w_l . (f_l(x) / |f_l(x)| - f_l(y) / |f_l(y)|)^2 )

f_l are VGG-16's relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 activations of the input scaled to [-1, 1]
and standardised by LPIPS's shift and scale; w_l >= 0 are the learned 1x1 "lin" layers. Two files are
needed: torchvision's ImageNet VGG-16 (``vgg16-397923af.pth``) and LPIPS's ``weights/v0.1/vgg.pth``.
``find_weights`` looks where those libraries keep them; ``EDMCGS_LPIPS_VGG`` / ``EDMCGS_LPIPS_LIN`` (or the
CLI's flags) point elsewhere.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from edmcgs.errors import InvalidInputError

VGG_FILE = "vgg16-397923af.pth"
"""torchvision's ImageNet VGG-16 weights, as its model hub caches them."""
VGG_LAYERS = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
"""VGG-16's convolutions ("M": 2x2 max-pool) up to relu5_3, in torchvision's ``features`` order."""
TAPS = (3, 8, 15, 22, 29)
"""Indices in ``features`` of relu1_2 ... relu5_3, the activations LPIPS compares."""
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

SKIPPED = (f"LPIPS (VGG) skipped: no weights on disk. It needs torchvision's {VGG_FILE} and LPIPS's "
           "weights/v0.1/vgg.pth (edmcgs never downloads them); give their paths with --lpips-vgg / "
           "--lpips-lin or EDMCGS_LPIPS_VGG / EDMCGS_LPIPS_LIN")


def _features() -> nn.Sequential:
    layers: list[nn.Module] = []
    channels = 3
    for spec in VGG_LAYERS:
        if spec == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(channels, spec, 3, padding=1), nn.ReLU()]
            channels = spec
    return nn.Sequential(*layers)


class LPIPS(nn.Module):
    """The metric; build with ``LPIPS.load`` (or from state dicts, for tests)."""

    def __init__(self, vgg_state: dict[str, Tensor], lin_state: dict[str, Tensor]):
        super().__init__()
        self.features = _features()
        wanted = {k for k in self.features.state_dict()}
        given = {k.removeprefix("features."): v for k, v in vgg_state.items() if k.startswith("features.")}
        missing = [f"features.{k}" for k in sorted(wanted - set(given))]
        if missing:
            raise InvalidInputError(f"LPIPS: the VGG-16 weights lack {', '.join(missing[:4])} (expected "
                                    f"torchvision's vgg16 state dict, {VGG_FILE})")
        self.features.load_state_dict({k: given[k] for k in wanted})
        lins = []
        for i, width in enumerate((64, 128, 256, 512, 512)):
            w = lin_state.get(f"lin{i}.model.1.weight")
            if w is None or tuple(w.shape) != (1, width, 1, 1):
                raise InvalidInputError(f"LPIPS: the lin weights lack lin{i}.model.1.weight of shape "
                                        f"[1, {width}, 1, 1] (expected LPIPS's weights/v0.1/vgg.pth)")
            lins.append(w.detach().float().reshape(width))
        self.lins = nn.ParameterList([nn.Parameter(w, requires_grad=False) for w in lins])
        self.register_buffer("shift", torch.tensor(SHIFT).reshape(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).reshape(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def load(cls, vgg_path: str | os.PathLike, lin_path: str | os.PathLike) -> LPIPS:
        """Read the two weight files (``torch.load(weights_only=True)``: no code runs from them)."""
        states = []
        for path in (vgg_path, lin_path):
            try:
                states.append(torch.load(path, map_location="cpu", weights_only=True))
            except (OSError, RuntimeError, pickle.UnpicklingError) as exc:
                raise InvalidInputError(f"LPIPS: cannot read weights {path}: {exc}") from exc
        return cls(*states)

    @torch.no_grad()
    def forward(self, image: Tensor, target: Tensor) -> Tensor:
        """image, target: Tensor  # [B, 3, H, W] float in [0, 1] -> [B] distances (0 for equal images)"""
        x = torch.cat([image, target]).float().clamp(0, 1)
        h = ((2 * x - 1) - self.shift) / self.scale
        total = torch.zeros(image.shape[0], device=image.device)
        taps = iter(zip(TAPS, self.lins, strict=True))
        tap, lin = next(taps)
        for i, layer in enumerate(self.features):
            h = layer(h)
            if i == tap:
                f = h / (h.square().sum(1, keepdim=True).sqrt() + 1e-10)
                a, b = f.chunk(2)
                total += torch.einsum("bchw,c->b", (a - b).square(), lin) / (h.shape[2] * h.shape[3])
                tap, lin = next(taps, (None, None))
                if tap is None:
                    break
        return total

    def score(self, image: np.ndarray, target: np.ndarray) -> float:
        """LPIPS of two [H, W, C] float images in [0, 1] (C = 1 is repeated to RGB)."""
        def batch(a: np.ndarray) -> Tensor:
            t = torch.as_tensor(np.asarray(a, np.float32)).permute(2, 0, 1)[None]
            return t.expand(1, 3, -1, -1) if t.shape[1] == 1 else t
        dev = self.shift.device
        return float(self(batch(image).to(dev), batch(target).to(dev))[0])


def _candidates(vgg, lin) -> list[tuple[str, Path | None, str]]:
    """(what, path or None when nowhere, where it was looked for) of the VGG and the lin weights.

    Given paths win (and must exist); then ``EDMCGS_LPIPS_VGG`` / ``EDMCGS_LPIPS_LIN``; then torch's hub
    cache (``$TORCH_HOME/hub/checkpoints``) and an installed ``lpips`` package's own linear weights.
    """
    def choose(given, env: str, fallback: Path | None) -> Path | None:
        path = given or os.environ.get(env)
        if path:
            if not Path(path).is_file():
                raise InvalidInputError(f"LPIPS weights {path} ({'given' if given else env}): no such file")
            return Path(path)
        return fallback if fallback is not None and fallback.is_file() else None

    torch_home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    hub = torch_home / "hub" / "checkpoints" / VGG_FILE
    spec = importlib.util.find_spec("lpips")  # finds the package without importing it (nor torchvision)
    lpips_dir = Path(spec.origin).parent if spec is not None and spec.origin else None
    own = lpips_dir / "weights" / "v0.1" / "vgg.pth" if lpips_dir else None
    lin_where = (f"not at {own} (the lpips package is installed without its weights)" if own else
                 "the lpips package is not installed (its wheel has them at lpips/weights/v0.1/vgg.pth)")
    return [(f"torchvision's ImageNet VGG-16 weights {VGG_FILE}", choose(vgg, "EDMCGS_LPIPS_VGG", hub),
             f"not at {hub} (put it there, or give --lpips-vgg PATH or EDMCGS_LPIPS_VGG)"),
            ("LPIPS's linear weights weights/v0.1/vgg.pth", choose(lin, "EDMCGS_LPIPS_LIN", own),
             f"{lin_where}; or give --lpips-lin PATH or EDMCGS_LPIPS_LIN")]


def find_weights(vgg: str | os.PathLike | None = None,
                 lin: str | os.PathLike | None = None) -> tuple[Path, Path] | None:
    """Paths of the two weight files, or None when either is absent (``missing_weights`` says which).

    Given paths win (and must exist); then ``EDMCGS_LPIPS_VGG`` / ``EDMCGS_LPIPS_LIN``; then torch's hub
    cache (``$TORCH_HOME/hub/checkpoints``) and an installed ``lpips`` package's own linear weights.
    """
    (_, vgg_path, _), (_, lin_path, _) = _candidates(vgg, lin)
    return (vgg_path, lin_path) if vgg_path and lin_path else None


def missing_weights(vgg: str | os.PathLike | None = None, lin: str | os.PathLike | None = None) -> str:
    """One line naming each weight file LPIPS still lacks and where to put it ('' when none is missing)."""
    gone = [f"{what}: {where}" for what, path, where in _candidates(vgg, lin) if path is None]
    if not gone:
        return ""
    return "LPIPS (VGG) skipped (edmcgs never downloads weights); missing " + "; ".join(gone)
