"""Bearer-token check shared by every route and the websocket (active only when a token is set)."""

from __future__ import annotations

import hmac
import re
from urllib.parse import unquote_plus

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


_QUERY = re.compile(r"\?([^\s\"#]*)")
SECRET_PARAMS = ("token",)


def redact_query(text: str) -> str:
    """``text`` with the value of every query parameter whose *decoded* name is a secret (``token``,
    ``tok%65n``, ``%74oken`` ...) replaced by ``***``."""
    if "?" not in text:
        return text

    def pairs(match: re.Match) -> str:
        out = []
        for pair in match.group(1).split("&"):
            name, eq, _value = pair.partition("=")
            if unquote_plus(name).strip().lower() in SECRET_PARAMS:
                pair = f"{name}{eq}***" if eq else pair
            out.append(pair)
        return "?" + "&".join(out)

    return _QUERY.sub(pairs, text)
