"""EdMCGS: event-driven Markov chain Gaussian splatting as a live streaming service.

Subpackages: ``edmcgs.sensor`` (event sources, ring buffer, event map), ``edmcgs.model`` (Gaussians,
rasterizer, deformation, training), ``edmcgs.synth`` (event simulator and synthetic benchmark),
``edmcgs.server`` (FastAPI service) and ``edmcgs.clients`` (Python client, browser viewer).
"""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("edmcgs")
except _metadata.PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
