"""numba compilation with an on-disk cache, shared by the numba kernels of ``render``.

numba keeps the cache beside the module (``__pycache__``) when that is writable and otherwise in the
user cache directory (``~/.cache/numba``), so a read-only install still compiles once per machine,
not once per process; numba's own ``NUMBA_CACHE_DIR`` overrides both (e.g. a container with a
read-only home). Where no location is writable the kernels compile once per process instead of
failing.
"""

from __future__ import annotations

import numba
import torch


def njit_cached(**options):
    """numba.njit with an on-disk cache where numba finds a writable place for one."""
    def wrap(fn):
        try:
            return numba.njit(cache=True, **options)(fn)
        except RuntimeError:  # numba: "cannot cache function ...: no locator available"
            return numba.njit(cache=False, **options)(fn)
    return wrap


def compiled(*kernels) -> bool:
    """Whether numba's on-disk cache holds every one of ``kernels`` (njit dispatchers) compiled from its
    current source: a process that finds them loads them in a fraction of a second, one that does not
    compiles them first (tens of seconds for the renderer), which a command announces. False where
    numba keeps no cache for a kernel."""
    for kernel in kernels:
        index = getattr(getattr(kernel, "_cache", None), "_cache_file", None)  # none: numba's NullCache
        if index is None or not index._load_index():  # {} when absent or stale (the source changed)
            return False
    return True


def in_torch_threads(kernel, *args, chunksize: int = 0):
    """``kernel(*args)``, a parallel numba kernel called from torch code, on torch's thread count (the
    trainer's ``--threads``, the server's ``torch_threads``). numba's OpenMP layer shares the
    process-wide OpenMP thread count with torch, so torch's is put back afterwards. chunksize: numba's
    parallel chunk size for this call (0: its default; 1: work items handed out one at a time)."""
    threads = torch.get_num_threads()
    previous_chunk = numba.set_parallel_chunksize(chunksize)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
        return kernel(*args)
    finally:
        numba.set_parallel_chunksize(previous_chunk)
        numba.set_num_threads(previous)
        torch.set_num_threads(threads)
