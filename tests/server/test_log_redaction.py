"""The token never reaches a log line: a corpus of its encodings in the query (quotes, ``&amp;``,
percent-encodings, duplicates, ``;`` separators, an encoded ``?``) sent raw to a real uvicorn serving
the app, with the command's log filter; every access and websocket line is read back."""

from __future__ import annotations

import logging
import socket
import threading
import time
from urllib.parse import quote, unquote, unquote_plus

import pytest

from edmcgs.server.settings import Settings
from harness.server import free_port
from tests.support.stub import StubService

SECRET = "Tk9secretVALUE"
WS_HEADERS = ("Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
              "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n")


def _spellings(secret: str) -> list[str]:
    every = "".join(f"%{ord(c):02X}" for c in secret)
    return [secret, quote(secret), every, every.lower(), "".join(f"%{ord(c):02x}" if i % 2 else c
                                                                 for i, c in enumerate(secret))]


def corpus(secret: str) -> list[str]:
    """Request targets carrying ``secret`` as a token, each a different spelling (>= 50)."""
    names = ["token", "TOKEN", "tok%65n", "%74oken", "%74%6F%6B%65%6E", "to+ken", "amp;token", "token[]",
             "%20token", "token%00"]
    values = _spellings(secret)
    queries = [f"{n}={values[i % len(values)]}" for i, n in enumerate(names)]
    queries += [f"token={v}" for v in values]
    queries += [
        f'a="&token={secret}', f'a="x"&token={secret}', f'token="{secret}"', f"x=1&amp;token={secret}",
        f"x=1&amp;amp;token={secret}", f"a=1;token={secret}", f"token={secret};a=1", f"a=1%26token={secret}",
        f"token=wrong&token={secret}", f"token={secret}&token={secret}", f"token=&token={secret}",
        f"t=0.5&token={secret}&w=8", f"token={secret}#frag", f"token%3D{secret}", f"{secret}",
        f"token={secret}%20", f"token=%22{secret}%22", f"token={secret}&a=%22", f"a=b?token={secret}",
        f"token={quote(quote(secret))}", f"a=\\\"&token={secret}", f"token={secret}&&", f"&&token={secret}",
        f"token=Bearer+{secret}", f"token=Bearer%20{secret}",
    ]
    targets = [f"/{path}?{q}" for i, q in enumerate(queries)
               for path in ("healthz", ("render", "nowhere")[i % 2])]
    targets += [f"/render%3Ftoken={secret}", f"/render%3Ftoken%3D{secret}", f"/healthz;token={secret}",
                f"/healthz%3Btoken={secret}", f"/render%253Ftoken%253D{secret}", f"/stream?token={secret}",
                f'/stream?a="&token={secret}', f"/stream?x=1&amp;token={secret}"]
    return targets


@pytest.fixture(params=["token", "no token"])
def server(request):
    import uvicorn

    from edmcgs.server.app import create_app
    from edmcgs.server.cli import RedactQueries

    token = SECRET if request.param == "token" else None
    app = create_app(Settings(token=token, allowed_hosts=["*"]), service_factory=StubService)
    lines: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            lines.append(self.format(record))

    config = uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_level="info", log_config=None,
                            timeout_graceful_shutdown=1)
    loggers = [logging.getLogger(n) for n in ("uvicorn.access", "uvicorn.error")]
    keep, redact = Keep(), RedactQueries(token)
    for logger in loggers:
        logger.addHandler(keep)
        logger.addFilter(redact)
        logger.setLevel(logging.INFO)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.02)
    try:
        yield config.port, lines, token
    finally:
        server.should_exit = True
        thread.join(10)
        for logger in loggers:
            logger.removeHandler(keep)
            logger.removeFilter(redact)


def _raw(port: int, target: str, websocket: bool) -> bytes:
    head = f"GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
    head += WS_HEADERS if websocket else "Connection: close\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head.encode("latin-1") + b"\r\n")
        data = s.recv(4096)
        if websocket and data.startswith(b"HTTP/1.1 101"):
            s.sendall(b"\x88\x82abcd" + bytes(a ^ b for a, b in zip(b"\x03\xe8", b"ab", strict=True)))
    return data


def test_the_secret_never_reaches_a_log_line(server):
    port, lines, token = server
    targets = corpus(SECRET)
    assert len(set(targets)) >= 50
    statuses = set()
    for k, target in enumerate(targets):
        answer = _raw(port, target, websocket="/stream" in target or k % 7 == 0)
        statuses.add(answer.split(b" ", 2)[1] if answer.startswith(b"HTTP/1.1 ") else b"closed")
    time.sleep(0.3)  # the last lines are written as their connections close
    assert len(lines) >= len(targets) // 2, lines
    assert statuses >= ({b"401", b"403"} if token else {b"101", b"200", b"404"}), statuses
    for line in lines:
        for seen in (line, unquote(line), unquote_plus(line), unquote(unquote(line))):
            assert SECRET.lower() not in seen.lower(), line
