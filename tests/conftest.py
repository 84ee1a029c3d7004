"""Suite-wide: every end-to-end module (``*_e2e.py``: real servers, the browser) is ``slow``, so that
``make check`` (``pytest -m "not slow"``) is the fast inner loop and ``make test`` still runs all."""

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name.endswith("_e2e.py"):
            item.add_marker(pytest.mark.slow)
