"""The API docs served by the app itself: Swagger UI, ReDoc and the websocket's AsyncAPI page load their
assets from the app (no CDN), the OpenAPI has a response schema for every route and the bearer scheme,
and the AsyncAPI document follows ``edmcgs.protocol`` (an app around a stub service; no model)."""

from __future__ import annotations

import dataclasses
import re
from urllib.parse import urljoin

import pytest
from fastapi.testclient import TestClient

from edmcgs import protocol
from edmcgs.server.app import create_app
from edmcgs.server.responses import TauRange
from edmcgs.server.settings import LOOPBACK, Settings
from tests.support.stub import StubService

TOKEN = "s3cret"
PAGES = ("/docs", "/redoc", "/asyncapi")


@pytest.fixture(params=[None, TOKEN], ids=["open", "token"])
def client(request):
    app = create_app(Settings(token=request.param, allowed_hosts=[*LOOPBACK, "testserver"]),
                     service_factory=StubService)
    with TestClient(app, base_url="http://127.0.0.1:8000") as c:
        c.token = request.param
        yield c


def linked(html: str) -> list[str]:
    """Every URL a page loads or links: src, href, and Swagger UI's url: '...'."""
    return re.findall(r'(?:src|href|spec-url)="([^"]+)"', html) + re.findall(r"url: '([^']+)'", html)


def refs(node) -> list[str]:
    if isinstance(node, dict):
        own = [node["$ref"]] if isinstance(node.get("$ref"), str) else []
        return own + [r for v in node.values() for r in refs(v)]
    if isinstance(node, list):
        return [r for v in node for r in refs(v)]
    return []


def resolves(doc: dict, ref: str) -> bool:
    node = doc
    for part in ref.removeprefix("#/").split("/"):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


@pytest.mark.parametrize("path", PAGES)
def test_docs_pages_load_everything_from_the_app_without_a_token(client, path):
    page = client.get(path)  # no Authorization header, with a token set or not: the docs hold no data
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    urls = linked(page.text)
    assert urls, "the page links nothing"
    assert not [u for u in urls if re.match(r"(https?:)?//", u)], f"{path} loads from another host"
    assert "cdn" not in page.text.lower() and "fonts.googleapis" not in page.text
    for url in urls:
        if url.startswith("#"):
            continue
        asset = client.get(urljoin(f"http://127.0.0.1:8000{path}", url))
        assert asset.status_code == 200 and len(asset.content) > 100, url


def test_the_docs_scripts_are_the_real_bundles(client):
    swagger = client.get("/docs/assets/swagger-ui-bundle.js")
    redoc = client.get("/docs/assets/redoc.standalone.js")
    assert "javascript" in swagger.headers["content-type"] and b"SwaggerUIBundle" in swagger.content
    assert "javascript" in redoc.headers["content-type"] and b"Redoc" in redoc.content
    assert "null" in client.get("/docs").text.split("validatorUrl")[1][:10]  # no schema sent to a validator
    if client.token:  # the docs' own files are open; nothing else under the prefix is
        assert client.get("/docs/assets/other.js").status_code == 401


def test_every_route_has_response_schemas_and_the_bearer_scheme(client):
    doc = client.get("/openapi.json").json()
    assert {"/render", "/scene", "/healthz", "/metrics", "/ply"} <= set(doc["paths"])  # and any new route:
    for path, operations in doc["paths"].items():
        for operation in operations.values():
            for status, response in operation["responses"].items():
                assert response.get("content"), f"{path} {status} has no content"
                for media, content in response["content"].items():
                    assert content.get("schema"), f"{path} {status} {media} has no schema"
            ok = operation["responses"]["200"]["content"]
            assert ok.get("application/json", {}).get("schema") or all(
                c["schema"].get("type") == "string" for c in ok.values()), path
            assert operation.get("security") == ([{"bearer": []}] if client.token else None), path
    scene = doc["paths"]["/scene"]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
    assert scene == {"$ref": "#/components/schemas/Scene"}
    assert doc["components"]["schemas"]["Scene"]["properties"]["tau_sources"]["items"] == {
        "$ref": "#/components/schemas/TauRange"}
    params = {p["name"]: p for p in doc["paths"]["/render"]["get"]["parameters"]}
    assert params["mode"]["schema"]["enum"] == list(protocol.RENDER_MODES)
    assert params["mode"]["schema"]["default"] == "rgb"
    assert "w FIRST" in params["pose"]["description"] and "qx qy qz qw" in params["pose"]["description"]
    bearer = doc["components"]["securitySchemes"]["bearer"]
    assert (bearer["type"], bearer["scheme"]) == ("http", "bearer")
    assert "EDMCGS_TOKEN" in bearer["description"]
    unresolved = [r for r in refs(doc) if not resolves(doc, r)]
    assert not unresolved


def test_open_probes_are_documented_without_the_lock():
    app = create_app(Settings(token=TOKEN, open_probes=True), service_factory=StubService)
    with TestClient(app, base_url="http://127.0.0.1:8000") as client:
        paths = client.get("/openapi.json").json()["paths"]
    assert "security" not in paths["/healthz"]["get"] and "security" not in paths["/metrics"]["get"]
    assert paths["/render"]["get"]["security"] == [{"bearer": []}]


def test_the_error_body_is_the_protocols(client):
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    body = schemas["ErrorBody"]
    assert set(body["properties"]) == set(protocol.ERROR_KEYS) == set(body["required"])
    assert schemas["ErrorCode"]["enum"] == [c.value for c in protocol.ErrorCode]
    assert set(schemas["ValidRange"]["properties"]) == set(protocol.ValidRange.__annotations__)
    answered = client.get("/render", params={"t": "soon"}, headers={"Authorization": f"Bearer {TOKEN}"})
    assert answered.status_code == 422 and set(answered.json()) == set(protocol.ERROR_KEYS)
    assert set(TauRange.model_fields) == set(protocol.TAU_SOURCE_KEYS)


def test_the_asyncapi_document_follows_the_protocol(client):
    doc = client.get("/asyncapi.json").json()
    assert doc["asyncapi"].startswith("3.") and doc["channels"]["stream"]["address"] == "/stream"
    schemas = doc["components"]["schemas"]
    sub = schemas["Subscription"]
    assert set(sub["properties"]) == {f.name for f in dataclasses.fields(protocol.Subscription)}
    assert all(p.get("description") for p in sub["properties"].values())  # every field documented
    assert sub["properties"]["format"]["enum"] == list(protocol.STREAM_FORMATS)
    assert sub["properties"]["mode"]["enum"] == list(protocol.STREAM_MODES)
    assert sub["properties"]["render_mode"]["enum"] == list(protocol.RENDER_MODES)
    assert "w first" in sub["properties"]["pose"]["description"]  # the quaternion's order, stated
    frame = schemas["Frame"]
    meta = protocol.FrameMeta(1, 0.0, 1, 0, 1.0, 8, 8, 3, "jpeg", "checkpoint", False)
    sent = meta.to_message(b"x", seq=0, dropped=0, arrived_unix_us=1, head_arrived_unix_us=2)
    assert list(frame["properties"]) == list(protocol.FRAME_KEYS) and set(sent) == set(frame["properties"])
    assert set(schemas["ErrorBody"]["properties"]) == set(protocol.ERROR_KEYS)
    messages = doc["components"]["messages"]
    assert set(messages) == {"subscription", "subscribed", "frame", "error", "end"}
    actions = {op["action"]: [m["$ref"].rsplit("/", 1)[1] for m in op["messages"]]
               for op in doc["operations"].values()}
    assert actions == {"send": ["subscription"], "receive": ["subscribed", "frame", "error", "end"]}
    for op in doc["operations"].values():
        assert ("security" in op) == (client.token is not None)
    assert not [r for r in refs(doc) if not resolves(doc, r)]
    page = client.get("/asyncapi").text
    for name in ("subscription", "frame", "seq", "dropped", "time_unavailable", "1013"):
        assert name in page


def test_a_subscription_echo_matches_its_schema(client):
    """The ``subscribed`` answer carries what the Subscription schema says, defaults included."""
    doc = client.get("/asyncapi.json").json()
    props = doc["components"]["schemas"]["Subscription"]["properties"]
    defaults = {k: p["default"] for k, p in props.items() if p.get("default") is not None}
    assert defaults == protocol.Subscription().to_message()


def test_the_pose_parameter_states_its_quaternion_order_and_the_tum_files(client, capsys):
    """A pose takes qw first and a TUM trajectory file qw last: each place that takes one says which."""
    from edmcgs.clients.export import main as export_main
    from edmcgs.train_cli import main as train_main

    params = client.get("/openapi.json").json()["paths"]["/render"]["get"]["parameters"]
    pose = next(p for p in params if p["name"] == "pose")["description"]
    assert "tx,ty,tz,qw,qx,qy,qz: the quaternion's w FIRST" in pose and "qx qy qz qw" in pose
    for main in (export_main, train_main):
        with pytest.raises(SystemExit):
            main(["--help"])
    shown = " ".join(capsys.readouterr().out.split())
    assert "tx,ty,tz,qw,qx,qy,qz: the quaternion's w FIRST" in shown
    assert "t tx ty tz qx qy qz qw, the quaternion's w LAST" in shown
