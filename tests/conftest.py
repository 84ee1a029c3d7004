"""Suite-wide: every end-to-end module (``*_e2e.py``: real servers, the browser) is ``slow``, so that
``make check`` (``pytest -m "not slow"``) is the fast inner loop and ``make test`` still runs all."""

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.name.endswith("_e2e.py"):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def browser():
    """One headless Debian Chromium for every browser test of the session (tests/support/viewer.py): a
    second playwright instance started while the first one lives is refused."""
    from tests.support.viewer import chromium

    with chromium() as browser:
        yield browser
