"""A real headless Chromium (Debian's) driven by playwright, for the browser viewer's tests.

Playwright's Python package only drives the browser: it is pointed at the system chromium and never
downloads one of its own.
"""

from __future__ import annotations

import pytest

from tests.support.viewer import MAX_SIZE, VIEW_H, VIEW_W, chromium


@pytest.fixture(scope="package")
def browser():
    """One browser for this folder's tests, closed when they end: playwright's sync API keeps an event
    loop running in the main thread, where a later test's asyncio.run would be refused, and a second
    playwright is refused while this one lives."""
    with chromium() as browser:
        yield browser


@pytest.fixture
def page(browser):
    """A fresh page at 1000x760 whose console errors and uncaught exceptions are collected."""
    context = browser.new_context(viewport={"width": 1000, "height": 760})
    page = context.new_page()
    page.errors = []
    page.on("pageerror", lambda exc: page.errors.append(f"uncaught: {exc}"))
    page.on("console", lambda msg: msg.type == "error" and page.errors.append(f"console: {msg.text}"))
    try:
        yield page
    finally:
        context.close()


# The real service for the viewer and export tests: the server tests' own helpers (a scene built with
# the model API, edmcgs-serve in a subprocess on a free loopback port), at a size worth looking at in
# a screenshot, with a token required and a width/height cap the tests can run into from the page.


@pytest.fixture(scope="package")
def served(tmp_path_factory):
    from harness.server import TOKEN, ServerProcess, build_scene

    rec, ckpt = build_scene(tmp_path_factory.mktemp("viewer-scene"), width=VIEW_W, height=VIEW_H,
                            event_rate=20_000, init_points=2000, control_points=64)
    srv = ServerProcess(["--replay", str(rec), "--checkpoint", str(ckpt), "--loop"],
                        env={"EDMCGS_TOKEN": TOKEN, "EDMCGS_MAX_WIDTH": str(MAX_SIZE),
                             "EDMCGS_MAX_HEIGHT": str(MAX_SIZE)})
    try:
        srv.wait_ready(TOKEN)
        srv.wait_streamed(1.9, TOKEN)  # the tests render anywhere in the recording's 2 s
        srv.token = TOKEN
        yield srv
    finally:
        srv.stop()
