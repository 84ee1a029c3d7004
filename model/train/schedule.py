"""Schedules of training as pure functions of progress (fraction of iterations done, in [0, 1])."""


def exp_decay(start: float, final_ratio: float, progress: float) -> float:
    """Log-linear decay from ``start`` to ``start * final_ratio`` (3DGS's learning-rate schedule)."""
    progress = min(max(progress, 0.0), 1.0)
    return start * final_ratio ** progress


def ramp(progress: float, begin: float, end: float) -> float:
    """0 before ``begin``, 1 after ``end``, linear in between (a step at ``begin`` when they are equal)."""
    if progress < begin:
        return 0.0
    if progress >= end:
        return 1.0
    return (progress - begin) / (end - begin)
