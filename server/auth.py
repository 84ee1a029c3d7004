"""Bearer-token check shared by every route and the websocket (active only when a token is set)."""

from __future__ import annotations

import hmac
from urllib.parse import quote, unquote

from edmcgs.server.errors import Unauthorized


def check_token(expected: str | None, authorization: str | None, query_token: str | None = None) -> None:
    """Raise Unauthorized unless ``authorization`` is ``Bearer <expected>`` (or, for websockets whose
    browser API cannot set headers, ``query_token`` equals it). No token configured: everything passes.
    """
    if expected is None:
        return
    given = None
    if authorization:
        scheme, _, value = authorization.partition(" ")
        if scheme.lower() == "bearer":
            given = value.strip()
    if given is None:
        given = query_token
    if given is None:
        raise Unauthorized("this server requires 'Authorization: Bearer <token>' (EDMCGS_TOKEN is set)")
    # Constant-time comparison: the token must not leak through response timing.
    if not hmac.compare_digest(given.encode(), expected.encode()):
        raise Unauthorized("wrong bearer token")


DECODE_ROUNDS = 4
"""Percent-decodings undone before a logged target is cut (``%253F`` is ``?`` twice encoded)."""


def loggable_target(target: str, token: str | None = None) -> str:
    """A request target as a log line may show it: its path alone, the query never, whatever it holds
    and however it is spelled (quotes, ``&amp;``, percent-encodings, duplicates, ``;`` separators). The
    target is percent-decoded (uvicorn logs the path re-encoded: an ``?`` inside it as ``%3F``), cut at
    the first ``?`` or ``;`` and encoded again; ``token``, should a client put it in the path itself,
    shows as ``***``."""
    text = target
    for _ in range(DECODE_ROUNDS):
        decoded = unquote(text)
        if decoded == text:
            break
        text = decoded
    cut = min((i for i in (text.find("?"), text.find(";")) if i >= 0), default=-1)
    if cut < 0 and text == target:
        shown = target
    else:
        shown = quote(text if cut < 0 else text[:cut], safe="/") + ("?..." if cut >= 0 else "")
    for spelled in {token, quote(token, safe="/")} if token else ():
        shown = shown.replace(spelled, "***")
    return shown
