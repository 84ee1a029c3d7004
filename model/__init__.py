"""EdMCGS: the model (Gaussians, control points, RGB prior, event-driven Markov transition), its
rendering, training, evaluation and checkpoints. Knows nothing of where events come from.

Rooms: ``render/`` (rasterizers and the float64 reference), ``motion/``, ``train/``, ``eval/``; beside
them ``dynamic`` (the ``EdMCGS`` module), ``config`` and ``checkpoint``. The public API is ``__all__``,
loaded on first use (importing a room does not import torch's whole model).
"""

from importlib import import_module

_EXPORTS = {
    "EdMCGS": "edmcgs.model.dynamic", "SceneMeta": "edmcgs.model.dynamic",
    "EdmcgsConfig": "edmcgs.model.config", "PRESETS": "edmcgs.model.config", "preset": "edmcgs.model.config",
    "load_checkpoint": "edmcgs.model.checkpoint", "save_checkpoint": "edmcgs.model.checkpoint",
    "read_checkpoint": "edmcgs.model.checkpoint",
    "Trainer": "edmcgs.model.train.trainer", "TrainingData": "edmcgs.model.data",
    "evaluate": "edmcgs.model.eval.evaluation", "summarize": "edmcgs.model.eval.evaluation",
    "rasterize": "edmcgs.model.render.rasterize", "rasterize_fast": "edmcgs.model.render.rasterize_fast",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'edmcgs.model' has no attribute {name!r}")
