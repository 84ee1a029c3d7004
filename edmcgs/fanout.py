"""Independent jobs as Ray tasks (the optional ``ray`` extra): ``edmcgs train --ray`` over several
recordings, ``bench.report --ray`` over its training grid.

Each task reserves ``threads`` CPUs and runs torch (and numba) on that many threads, so tasks side by
side never oversubscribe the cores Ray gave them. Results come back in the jobs' order; files a job
writes (checkpoints, caches) land where it writes them, which on one machine is where the sequential
run would have put them (on a cluster: give paths on storage every node mounts).

Joins the cluster at ``RAY_ADDRESS`` when set, else starts a local Ray for the call and shuts it down
after; a Ray already initialised by the caller is used as it is.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from edmcgs.errors import InvalidInputError


def _with_threads(fn: Callable[[Any], Any], job: Any, threads: int) -> Any:
    """Runs in the task's worker: its own thread counts, then the job."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except (ImportError, ValueError):
        pass
    return fn(job)


def fan_out(fn: Callable[[Any], Any], jobs: Sequence[Any], *, threads: int = 1,
            num_cpus: int | None = None) -> list[Any]:
    """``[fn(job) for job in jobs]``, each call a Ray task with ``threads`` CPUs; ``num_cpus``: the
    size of the local Ray started here (default: every core). A failed job raises its own error."""
    if threads < 1:
        raise InvalidInputError(f"threads per task must be >= 1, got {threads}")
    try:
        import ray
    except ImportError as exc:
        raise InvalidInputError(f"--ray needs the 'ray' extra (pip install 'edmcgs[ray]'): {exc}") from None
    if not jobs:
        return []
    started_here = not ray.is_initialized()
    if started_here:
        joined = bool(os.environ.get("RAY_ADDRESS"))
        ray.init(num_cpus=None if joined else num_cpus, include_dashboard=False)
    try:
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus < threads:
            raise InvalidInputError(f"a task wants {threads} CPUs but the Ray cluster has {cpus:g}")
        task = ray.remote(num_cpus=threads, max_retries=0)(_with_threads)
        refs = [task.remote(fn, job, threads) for job in jobs]
        try:
            return ray.get(refs)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            raise cause from None
    finally:
        if started_here:
            ray.shutdown()
