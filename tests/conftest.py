"""Suite-wide marks.

- Every end-to-end module (``*_e2e.py``: real servers, the browser) is ``slow``, so that ``make check``
  (``pytest -m "not slow"``) is the fast inner loop and ``make test`` still runs all.
- ``make test`` runs on two pytest-xdist workers (``--dist loadgroup``): each module is one group, so its
  tests share one worker and its module-scoped fixtures are built once; every module that starts a local
  Ray is in the group ``ray``, so two Ray clusters never share the machine's cores.
"""

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name.endswith("_e2e.py"):
            item.add_marker(pytest.mark.slow)
        group = "ray" if "ray" in item.path.stem.split("_") else str(item.path)
        item.add_marker(pytest.mark.xdist_group(group))
