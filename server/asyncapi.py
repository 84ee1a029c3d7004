"""The websocket protocol (``WS /stream``) as an AsyncAPI 3.0 document, and that document as a plain HTML
page: served beside /docs at ``/asyncapi.json`` and ``/asyncapi``. The message schemas come from the
protocol's types (``wire_schema``), the limits and close codes from the route itself, so neither can
drift from what the server does.
"""

from __future__ import annotations

import html
import json
import re

from edmcgs import protocol
from edmcgs.server import wire_schema
from edmcgs.server.openapi import BEARER, bearer_scheme
from edmcgs.server.routes.stream import (
    CLOSE_INTERNAL_ERROR,
    CLOSE_POLICY,
    CLOSE_TRY_AGAIN_LATER,
    MIN_FPS,
    SUBSCRIBE_WAIT_S,
)
from edmcgs.server.settings import Settings

"""Close code of a websocket refused before its handshake (missing or wrong token, foreign Host or
Origin); ``middleware.AccessMiddleware`` sends it."""

_MESSAGES = {  # name -> (schema, direction, summary)
    "subscription": ("Subscription", "send", "Ask for frames: live (follow the head) or sweep (t0..t1); "
                                             "a msgpack map (binary message) or a JSON object (text)."),
    "subscribed": ("Subscribed", "receive", "The subscription now in force, after each accepted one."),
    "frame": ("Frame", "receive", "A rendered frame, at the subscription's rate."),
    "error": ("ErrorBody", "receive", "A refused subscription (the previous one stays in force) or a "
                                      "frame that could not be rendered; the connection stays open."),
    "end": ("End", "receive", "A sweep without loop is done."),
}


def document(settings: Settings, version: str) -> dict:
    """The AsyncAPI 3.0 document of this server's websocket."""
    token_set = settings.token is not None
    ref = wire_schema.REF_TEMPLATE.format
    messages = {
        name: {"name": name, "title": schema, "summary": summary, "payload": {"$ref": ref(model=schema)}}
        for name, (schema, _direction, summary) in _MESSAGES.items()}
    channel_messages = {name: {"$ref": f"#/components/messages/{name}"} for name in messages}

    def operation(action: str, summary: str) -> dict:
        op = {"action": action, "channel": {"$ref": "#/channels/stream"}, "summary": summary,
              "messages": [{"$ref": f"#/channels/stream/messages/{name}"}
                           for name, (_, direction, _) in _MESSAGES.items() if direction == action]}
        if token_set:
            op["security"] = [{"$ref": f"#/components/securitySchemes/{BEARER}"}]
        return op

    return {
        "asyncapi": "3.0.0",
        "info": {"title": "edmcgs stream", "version": version, "description": _DESCRIPTION.format(
            max_fps=settings.stream_max_fps, min_fps=MIN_FPS, max_streams=settings.max_streams,
            max_bytes=protocol.MAX_MESSAGE_BYTES, subscribe_wait_s=SUBSCRIBE_WAIT_S)},
        "defaultContentType": "application/msgpack",
        "channels": {"stream": {
            "address": "/stream", "title": "WS /stream", "messages": channel_messages,
            "description": "One connection, one subscription at a time (re-sent whole or in part to "
                           "change it). Close codes: " + ", ".join(
                               f"{code} {why}" for code, why in _close_codes()),
            "bindings": {"ws": {"query": {"type": "object", "properties": {"token": {
                "type": "string", "description": "EDMCGS_TOKEN, where the client cannot set an "
                                                 "Authorization header (a browser)"}}}}}}},
        "operations": {
            "subscribe": operation("send", "Send a subscription (msgpack binary or JSON text)."),
            "receive": operation("receive", "Receive msgpack maps, each with a type: subscribed, "
                                            "frame, error or end."),
        },
        "components": {
            "messages": messages,
            "schemas": wire_schema.schemas(),
            "securitySchemes": {BEARER: bearer_scheme(token_set)},
        },
    }


_DESCRIPTION = """Frames pushed by the server over `WS /stream`, following the live head of the event stream
or sweeping a time range.

The client sends a subscription (a msgpack map as a binary message or a JSON object as a text message, at
most {max_bytes} bytes); each is answered by `subscribed` or `error`. Frames come at the subscription's
fps ({min_fps:g} to {max_fps:g} on this server). A client that reads slower than that gets fewer: a frame
is rendered only once the previous one is sent, the ones skipped meanwhile counted in each frame's
`dropped`. This server serves at most {max_streams} streams at once; one more is sent a `busy` error and
closed with 1013. A stream without a subscription for {subscribe_wait_s:g} s (from its opening or a sweep's
end) is sent an `error` and closed with 1008; one that stops reading (and answering pings) is dropped.

Time: `t` is seconds from the scene's start (`t_start_us` of GET /scene), `t_us` absolute microseconds on
the checkpoint's clock; every frame carries both. The same types are the Python module `edmcgs.protocol`."""


def _close_codes() -> list[tuple[int, str]]:
    return [(CLOSE_POLICY, "refused before the handshake (token, foreign Host or Origin), or no "
                           "subscription in force for a while (after an error message)"),
            (CLOSE_INTERNAL_ERROR, "the stream failed (after an error message saying how)"),
            (CLOSE_TRY_AGAIN_LATER, "too many streams (after a busy error message), or too many requests "
                                     "in progress (max_connections, before the handshake)")]


# ------------------------------------------------------------------------------------------ the page

def page(doc: dict) -> str:
    """``doc`` as a self-contained HTML page (no script, no external resource)."""
    schemas = doc["components"]["schemas"]
    info, channel = doc["info"], doc["channels"]["stream"]
    parts = [f"<h1>{_e(info['title'])} <small>AsyncAPI {_e(doc['asyncapi'])}, version "
             f"{_e(info['version'])}</small></h1>",
             '<p>This page shows <a href="asyncapi.json">asyncapi.json</a>; the HTTP routes are in '
             '<a href="docs">/docs</a> and <a href="redoc">/redoc</a>.</p>',
             _paragraphs(info["description"]),
             f"<h2>{_e(channel['title'])}</h2>", _paragraphs(channel["description"])]
    for op_name, op in doc["operations"].items():
        who = "Client → server" if op["action"] == "send" else "Server → client"
        parts.append(f'<h2 id="{_e(op_name)}">{who}</h2><p>{_e(op["summary"])}</p>')
        if "security" in op:
            parts.append("<p>Needs the bearer token (<code>Authorization: Bearer …</code> or "
                         "<code>?token=</code>).</p>")
        for ref in op["messages"]:
            message = doc["components"]["messages"][ref["$ref"].rsplit("/", 1)[1]]
            name = message["payload"]["$ref"].rsplit("/", 1)[1]
            parts.append(f'<h3 id="{_e(message["name"])}">{_e(message["name"])}</h3>'
                         f"<p>{_e(message['summary'])}</p>{_schema_table(schemas[name], schemas)}")
    codes = schemas["ErrorCode"]["enum"]
    parts.append("<h2>Error codes</h2><table><tr><th>error</th><th>HTTP status</th></tr>" + "".join(
        f"<tr><td><code>{_e(c)}</code></td><td>{protocol.STATUS[protocol.ErrorCode(c)]}</td></tr>"
        for c in codes) + "</table>")
    parts.append("<h2>Schemas</h2>" + "".join(
        f'<h3 id="schema-{_e(n)}">{_e(n)}</h3>{_schema_table(s, schemas)}' for n, s in schemas.items()
        if s.get("type") == "object" and n not in {m[0] for m in _MESSAGES.values()}))
    return _PAGE.format(title=_e(info["title"]), body="\n".join(parts))


def _schema_table(schema: dict, schemas: dict) -> str:
    if "properties" not in schema:
        return f"<p>{_text(schema.get('description', ''))}</p>"
    required = set(schema.get("required", ()))
    rows = []
    for name, prop in schema["properties"].items():
        default = f"<code>{_e(json.dumps(prop['default']))}</code>" if "default" in prop else ""
        rows.append(f"<tr><td><code>{_e(name)}</code>{' *' if name in required else ''}</td>"
                    f"<td>{_type_text(prop)}</td><td>{default}</td>"
                    f"<td>{_text(_description(prop, schemas))}</td></tr>")
    head = "<tr><th>field (* required)</th><th>type</th><th>default</th><th>description</th></tr>"
    return f"<p>{_text(schema.get('description', ''))}</p><table>{head}{''.join(rows)}</table>"


def _description(prop: dict, schemas: dict) -> str:
    if "description" in prop:
        return prop["description"]
    target = prop.get("$ref") or next((o["$ref"] for o in prop.get("anyOf", ()) if "$ref" in o), None)
    return "" if target is None else schemas[target.rsplit("/", 1)[1]].get("description", "")


def _type_text(prop: dict) -> str:
    """A JSON Schema type in a few characters of HTML."""
    if "$ref" in prop:
        name = prop["$ref"].rsplit("/", 1)[1]
        return f'<a href="#schema-{_e(name)}">{_e(name)}</a>'
    if "const" in prop:
        return f"<code>{_e(json.dumps(prop['const']))}</code>"
    if "enum" in prop:
        return " | ".join(f"<code>{_e(json.dumps(v))}</code>" for v in prop["enum"])
    if "anyOf" in prop:
        return " | ".join(_type_text(option) for option in prop["anyOf"])
    kind = prop.get("type", "any")
    if isinstance(kind, list):
        return " | ".join(_e(k) for k in kind)
    if kind == "array":
        return f"array of {_type_text(prop.get('items', {}))}"
    if prop.get("format") == "binary":
        return "bytes"
    return _e(kind)


def _paragraphs(text: str) -> str:
    """Plain text with `code` spans as HTML paragraphs."""
    return "".join(f"<p>{_text(p)}</p>" for p in text.split("\n\n"))


def _text(text: str) -> str:
    """Escaped text, its ``code`` and `code` spans as HTML."""
    return re.sub(r"``(.+?)``|`([^`]+)`", lambda m: f"<code>{m.group(1) or m.group(2)}</code>", _e(text))


def _e(text: object) -> str:
    return html.escape(str(text))


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}: websocket protocol</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body {{ font: 15px/1.5 system-ui, sans-serif; max-width: 980px; margin: 2em auto; padding: 0 1em; }}
table {{ border-collapse: collapse; width: 100%; margin: .5em 0 1.5em; }}
th, td {{ border: 1px solid #ccc; padding: .3em .5em; text-align: left; vertical-align: top; }}
th {{ background: #f4f4f4; }} small {{ color: #666; font-weight: normal; }}
code {{ background: #f4f4f4; padding: 0 .2em; }}
</style></head>
<body>
{body}
</body></html>
"""
