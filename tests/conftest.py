"""Suite-wide marks and how ``make test``'s two pytest-xdist workers share the suite.

- Every end-to-end module (``*_e2e.py``: real servers, the browser) is ``slow``, so that ``make check``
  (``pytest -m "not slow"``) is the fast inner loop and ``make test`` still runs all.
- Each module runs whole on one worker, so that its module-scoped fixtures (servers, Ray clusters,
  trained scenes) are built once; every module that starts a local Ray is one unit, so that two Ray
  clusters never share the machine's cores. The grouping is this scheduler's own (``group``):
  pytest-xdist's ``xdist_group`` mark works by renaming node ids, which pytest 9.2 no longer allows, and
  then split every module over both workers.
"""

import pytest


def group(nodeid: str) -> str:
    """The unit of work a test belongs to: "ray" for the modules that start a local Ray, else its module."""
    path = nodeid.split("::", 1)[0]
    stem = path.rsplit("/", 1)[-1].removesuffix(".py")
    return "ray" if "ray" in stem.split("_") else path


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name.endswith("_e2e.py"):
            item.add_marker(pytest.mark.slow)


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):
        """Whole groups to a worker, the groups with most tests first (xdist's loadscope order)."""

        def _split_scope(self, nodeid: str) -> str:
            return group(nodeid)

    return ByGroup(config, log)
