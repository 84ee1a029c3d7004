"""Torch devices named by users (``--device``, ``EDMCGS_DEVICE``): checked before anything is built."""

from __future__ import annotations

from edmcgs.errors import InvalidInputError


def check_device(name: str) -> str:
    """``name`` if this machine has that torch device, else InvalidInputError in one line saying what it has.

    'cpu', 'cuda', 'cuda:N' (N < the number of GPUs), 'mps' where torch has it; nothing else.
    """
    text = str(name).strip()
    if text == "cpu":  # every torch has it: no need to import torch (a command's checks stay instant)
        return text
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise InvalidInputError(f"unknown torch device {text!r}: use cpu, cuda or cuda:N") from None
    available = ["cpu"]
    if torch.cuda.is_available():
        available += ["cuda"] + [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        available.append("mps")
    if device.type == "cpu":
        return text
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is a CPU build" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise InvalidInputError(f"device {text!r} is not available ({why}); available: "
                                    f"{', '.join(available)}")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InvalidInputError(f"device {text!r} does not exist; available: {', '.join(available)}")
        return text
    if device.type == "mps" and "mps" in available:
        return text
    raise InvalidInputError(f"device {text!r} is not available; available: {', '.join(available)}")
