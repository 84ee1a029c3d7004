"""numba compilation with an on-disk cache, shared by the numba kernels of ``render``.

numba keeps the cache beside the module (``__pycache__``) when that is writable and otherwise in the
user cache directory (``~/.cache/numba``), so a read-only install still compiles once per machine,
not once per process; numba's own ``NUMBA_CACHE_DIR`` overrides both (e.g. a container with a
read-only home). Where no location is writable the kernels compile once per process instead of
failing.
"""

from __future__ import annotations

import numba


def njit_cached(**options):
    """numba.njit with an on-disk cache where numba finds a writable place for one."""
    def wrap(fn):
        try:
            return numba.njit(cache=True, **options)(fn)
        except RuntimeError:  # numba: "cannot cache function ...: no locator available"
            return numba.njit(cache=False, **options)(fn)
    return wrap
