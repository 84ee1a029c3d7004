"""Deterministic stand-in weights for LPIPS tests (torch only: the cross-check against the reference
``lpips`` package imports this file from another environment)."""

import math

import torch

VGG_CONVS = ((0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256), (12, 256, 256),
             (14, 256, 256), (17, 256, 512), (19, 512, 512), (21, 512, 512), (24, 512, 512), (26, 512, 512),
             (28, 512, 512))
"""(index in torchvision's vgg16 ``features``, in channels, out channels) of each 3x3 convolution."""


def random_weights(seed: int = 0) -> tuple[dict, dict]:
    """(VGG-16 state dict in torchvision's key layout, LPIPS lin state dict): He-scaled random convolutions
    (activations stay O(1) through 13 layers) and non-negative lin weights."""
    g = torch.Generator().manual_seed(seed)
    vgg = {}
    for idx, cin, cout in VGG_CONVS:
        vgg[f"features.{idx}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * math.sqrt(2 / (9 * cin))
        vgg[f"features.{idx}.bias"] = 0.1 * torch.randn(cout, generator=g)
    lin = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) * 0.05
           for i, c in enumerate((64, 128, 256, 512, 512))}
    return vgg, lin


def image_pair(seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """[3, 3, 48, 64] images in [0, 1] and a noisy copy; the third pair is identical."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(3, 3, 48, 64, generator=g)
    b = (a + 0.2 * torch.randn(3, 3, 48, 64, generator=g)).clamp(0, 1)
    b[2] = a[2]
    return a, b
