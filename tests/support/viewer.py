"""What the browser tests share: where the viewer's files are, the served scene's size, and Debian's
headless Chromium driven by playwright (which never downloads a browser of its own)."""

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

VIEWER = Path(__file__).resolve().parents[2] / "clients" / "viewer"
VIEW_W, VIEW_H = 160, 120
"""The viewer tests' scene, a size worth looking at in a screenshot."""
MAX_SIZE = 200
"""The server's width / height cap in the viewer tests (the page can run into it)."""

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def chromium_path() -> str:
    if CHROMIUM.exists():
        return str(CHROMIUM)
    found = shutil.which("chromium")
    if found is None:
        pytest.fail("Debian's chromium is not installed: scripts/bootstrap.sh --test installs it (apt-get)")
    return found


@contextmanager
def chromium() -> Iterator:
    """A headless Debian Chromium under playwright, closed on exit."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium_path(), headless=True, args=ARGS)
        try:
            yield browser
        finally:
            browser.close()
