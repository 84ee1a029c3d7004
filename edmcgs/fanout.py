"""Independent jobs as Ray tasks (the optional ``ray`` extra): ``edmcgs train --ray`` over several
recordings, ``bench.report --ray`` over its training grid; and the Ray session both these and the
data-parallel training (``edmcgs.data_parallel``) run in.

Each task reserves ``threads`` CPUs and runs torch (and numba) on that many threads, so tasks side by
side never oversubscribe the cores Ray gave them. Results come back in the jobs' order; files a job
writes (checkpoints, caches) land where it writes them, which on one machine is where the sequential
run would have put them (on a cluster: give paths on storage every node mounts).

Joins the cluster at ``RAY_ADDRESS`` when set, else starts a local Ray for the call and shuts it down
after; a Ray already initialised by the caller is used as it is.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from edmcgs.errors import InvalidInputError


def with_threads(fn: Callable[[Any], Any], job: Any, threads: int) -> Any:
    """Runs in a Ray worker: its own thread counts, then the job."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except (ImportError, ValueError):
        pass
    return fn(job)


@contextmanager
def ray_session(num_cpus: int | None = None) -> Iterator[Any]:
    """The ``ray`` module, initialised for the block: joins ``RAY_ADDRESS`` when set, else a local Ray of
    ``num_cpus`` (default: every core), shut down after it; a Ray the caller initialised is used as it is."""
    try:
        import ray
    except ImportError as exc:
        raise InvalidInputError(f"--ray needs the 'ray' extra (pip install 'edmcgs[ray]'): {exc}") from None
    started_here = not ray.is_initialized()
    if started_here:
        joined = bool(os.environ.get("RAY_ADDRESS"))
        ray.init(num_cpus=None if joined else num_cpus, include_dashboard=False)
    try:
        yield ray
    finally:
        if started_here:
            ray.shutdown()


def check_cpus(ray, wanted: float, what: str) -> None:
    """InvalidInputError unless the cluster has ``wanted`` CPUs (``what`` wants them)."""
    cpus = ray.cluster_resources().get("CPU", 0)
    if cpus < wanted:
        raise InvalidInputError(f"{what} wants {wanted:g} CPUs but the Ray cluster has {cpus:g}")


def fan_out(fn: Callable[[Any], Any], jobs: Sequence[Any], *, threads: int = 1,
            num_cpus: int | None = None) -> list[Any]:
    """``[fn(job) for job in jobs]``, each call a Ray task with ``threads`` CPUs; ``num_cpus``: the
    size of the local Ray started here (default: every core). A failed job raises its own error."""
    if threads < 1:
        raise InvalidInputError(f"threads per task must be >= 1, got {threads}")
    if not jobs:
        return []
    with ray_session(num_cpus) as ray:
        check_cpus(ray, threads, "a task")
        task = ray.remote(num_cpus=threads, max_retries=0)(with_threads)
        refs = [task.remote(fn, job, threads) for job in jobs]
        try:
            return ray.get(refs)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause if getattr(exc, "cause", None) is not None else exc
            raise cause from None
