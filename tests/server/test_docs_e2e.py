"""The API docs in a real browser against a real uvicorn server, with every request to another host
refused: Swagger UI and ReDoc render the API from the app's own assets, the Authorize button sends the
bearer token, and the websocket protocol's page shows its messages. Debian's headless Chromium, driven by
playwright (which never downloads a browser)."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest

from edmcgs.server.app import create_app
from edmcgs.server.settings import Settings
from harness.server import ThreadServer
from tests.support.stub import StubService
from tests.support.viewer import chromium

pytestmark = pytest.mark.slow

TOKEN = "docs-token"


@pytest.fixture(scope="module")
def served():
    app = create_app(Settings(token=TOKEN), service_factory=StubService)
    with ThreadServer(app) as server:
        yield server


@pytest.fixture(scope="module")
def browser():
    with chromium() as browser:
        yield browser


@pytest.fixture
def page(browser, served):
    """A page that may load from the served app only: anything else is aborted and recorded."""
    context = browser.new_context(viewport={"width": 1100, "height": 900})
    page = context.new_page()
    page.foreign, page.errors = [], []
    ours = urlsplit(served.url).netloc

    def route(r):
        if urlsplit(r.request.url).netloc == ours or r.request.url.startswith("data:"):
            r.continue_()
        else:
            page.foreign.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    page.on("pageerror", lambda exc: page.errors.append(f"uncaught: {exc}"))
    # A request the page's Content-Security-Policy stops never reaches the network: recorded here.
    page.on("console", lambda msg: "Content Security Policy" in msg.text and page.blocked.append(msg.text))
    page.blocked = []
    try:
        yield page
    finally:
        context.close()


def test_swagger_ui_renders_the_api_and_authorizes_with_the_token(page, served, tmp_path):
    page.goto(served.url + "/docs")
    page.locator(".opblock-summary-path", has_text="/render").first.wait_for(timeout=30_000)
    paths = set(page.locator(".opblock-summary-path").all_inner_texts())
    assert {"/render", "/scene", "/healthz", "/metrics", "/ply"} <= {p.strip() for p in paths}
    page.locator("button.authorize").first.click()
    page.locator(".modal-ux input").first.fill(TOKEN)
    page.locator(".modal-ux button.authorize").first.click()
    page.locator(".modal-ux button.close-modal").first.click()
    health = page.locator(".opblock", has=page.locator(".opblock-summary-path", has_text="/healthz"))
    health.locator(".opblock-summary").click()
    health.locator("button.try-out__btn").click()
    health.locator("button.execute").click()
    status = health.locator(".live-responses-table tbody .response-col_status").first
    status.wait_for(timeout=30_000)
    assert status.inner_text().strip().startswith("200")  # the token went with the request
    assert f"Authorization: Bearer {TOKEN}" in health.locator(".curl-command").inner_text()
    page.screenshot(path=str(tmp_path / "swagger.png"))
    assert not (page.foreign or page.errors or page.blocked), (page.foreign, page.errors, page.blocked)


def test_redoc_renders_the_api_offline(page, served, tmp_path):
    page.goto(served.url + "/redoc")
    page.get_by_text("Render the scene at time t from a pose").first.wait_for(timeout=60_000)
    assert page.get_by_text("The Gaussians at time t as a 3DGS PLY file").count() >= 1
    page.screenshot(path=str(tmp_path / "redoc.png"))
    assert not page.foreign and not page.errors, (page.foreign, page.errors)
    # ReDoc's footer logo is on a CDN; the policy keeps the browser from asking for it, nothing else
    assert all("cdn.redoc.ly" in b for b in page.blocked), page.blocked


def test_the_websocket_protocol_page(page, served):
    page.goto(served.url + "/asyncapi")
    assert "AsyncAPI" in page.locator("h1").inner_text()
    for anchor in ("subscription", "frame", "error", "end", "subscribed"):
        assert page.locator(f"h3#{anchor}").count() == 1
    assert page.locator("a[href='asyncapi.json']").count() == 1
    assert not (page.foreign or page.errors or page.blocked), (page.foreign, page.errors, page.blocked)
