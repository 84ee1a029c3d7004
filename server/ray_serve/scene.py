"""A render replica of one scene: the single-process service (its source, ring, deformation cache and
render pool) running in-process, answering the gateway's forwarded requests and websocket sessions.

A replica whose checkpoint or source fails to open stays up and says so: its ``/healthz`` answers 503
with the error (``source: "error"``), every other route 503 ``not_ready``. Failing its constructor
instead would have Serve restart it in a loop and mark the whole application failed; this way the
failure stays the scene's own and the other scenes keep serving.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from collections.abc import AsyncIterator

from edmcgs import protocol
from edmcgs.server.ray_serve.asgi import HttpResult, WebSocketSession, WsMessage, http_request

log = logging.getLogger("edmcgs.server.ray")


SPAN_WAIT_S = 60.0
"""Longest a replay's replica waits for its replay to cover the checkpoint's span before serving."""
SPAN_SLACK_US = 20_000
"""The span counts as covered this close to its end (the last replay batch may end just short of it)."""
REPLICA_HEADER = "X-Edmcgs-Replica"
"""Response header naming the replica that answered (its Ray actor's name, in Serve's namespace)."""


def _replica_name() -> str:
    """This replica's actor name (``ray.get_actor(name, namespace="serve")`` finds it)."""
    from ray import serve

    try:
        return serve.get_replica_context().replica_id.to_full_id_str()
    except Exception:  # constructed outside Serve (a unit test)
        return "local"


class SceneReplica:
    """Serve deployment class of a scene (``app.py`` wraps it with ``serve.deployment``)."""

    async def __init__(self, name: str, settings: dict, ingest=None, learner=None):
        # As edmcgs-serve does, before torch and numba start their pools (see server/cli.py).
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        from edmcgs.errors import EdmcgsError
        from edmcgs.server.app import create_app
        from edmcgs.server.service import Service
        from edmcgs.server.settings import Settings

        self.name = name
        self.replica = _replica_name()
        self.failure: str | None = None
        self.started_unix = time.time()
        self._service = None
        self.app = None
        self._token: str | None = None
        self._probe_host = "localhost"
        self._pusher: asyncio.Task | None = None
        try:
            parsed = Settings(**settings)
            source = None
            if ingest is not None:  # a live scene: its one source, shared by every replica
                from edmcgs.server.ray_serve.shared_source import RemoteSource

                source = await asyncio.to_thread(RemoteSource, ingest, name)
            learning = None
            if learner is not None:  # a cold start: the scene's one learner, its models swapped in here
                from functools import partial

                from edmcgs.server.ray_serve.learner import RemoteLearning

                learning = partial(RemoteLearning, learner)
            self._service = await asyncio.to_thread(Service.open, parsed, source, learning)
        except (EdmcgsError, OSError, ValueError) as exc:
            self.failure = f"{type(exc).__name__}: {exc}"
            log.error("scene %s failed to open: %s", name, self.failure)
            return
        service = self._service
        self._token = parsed.token.get_secret_value() if parsed.token is not None else None
        self._probe_host = probe_host(parsed.host_allowlist)
        self.app = create_app(parsed, service_factory=lambda _settings: service)
        # The app's lifespan starts the ingest thread and binds the service to this replica's loop.
        self._lifespan = self.app.router.lifespan_context(self.app)
        await self._lifespan.__aenter__()
        await self._await_span(parsed)
        self._pusher = asyncio.create_task(self._push_metrics())
        log.info("scene %s: replica ready", name)

    async def _push_metrics(self) -> None:
        """Send this replica's exposition to the gateway's board (``scrape.py``) while it lives."""
        import ray
        from ray import serve

        from edmcgs.server.ray_serve.scrape import BOARD_NAME, PUSH_PERIOD_S

        try:
            board_name = BOARD_NAME.format(app=serve.get_replica_context().app_name)
        except Exception:  # constructed outside Serve: nobody to push to
            return
        board = None
        while True:
            try:
                if board is None:
                    board = ray.get_actor(board_name, namespace="serve")
                result = await self.probe("/metrics")
                await board.push.remote(self.name, self.replica, result.body.decode())
            except ValueError:  # the gateway has not made its board yet
                pass
            except Exception as exc:  # the board went with its gateway: find the next one
                log.debug("scene %s: metrics not pushed (%s)", self.name, type(exc).__name__)
                board = None
            await asyncio.sleep(PUSH_PERIOD_S)

    async def _await_span(self, settings) -> None:
        """A replay's replica takes traffic once its own replay has covered the checkpoint's span, so a
        replacement renders the times its siblings do (a new replica replays from the start; without
        this, a retried render could meet 416 where the dead replica answered). A live camera's or a
        sensorless replica waits for nothing."""
        service = self._service
        if service.source is None or service.source.info.live:
            return
        meta = service.engine.meta
        budget = min(SPAN_WAIT_S, (meta.t_end_us - meta.t_start_us) / 1e6 / settings.speed + 5.0)
        deadline = time.monotonic() + budget
        while time.monotonic() < deadline:
            ranges = service.engine.renderable()
            if ranges and ranges[-1][1] >= meta.t_end_us - SPAN_SLACK_US:
                return
            await asyncio.sleep(0.05)
        log.warning("scene %s: the replay did not cover the span in %.0f s; serving what it has", self.name,
                    budget)

    def __del__(self):
        pusher = getattr(self, "_pusher", None)
        if pusher is not None:
            pusher.cancel()
        service, self._service = getattr(self, "_service", None), None
        if service is not None:
            service.close()

    def check_health(self) -> None:
        """Serve's periodic probe: a replica is healthy while it answers; a scene's failure is reported
        on its own health route, never by restarting the replica."""

    def _failed(self, path: str) -> HttpResult:
        if path == "/healthz":
            body = {"ready": False, "model": "not loaded", "source": "error", "source_error": self.failure,
                    "uptime_s": round(time.time() - self.started_unix, 3)}
        else:
            body = protocol.ErrorBody(protocol.ErrorCode.NOT_READY,
                                      f"scene {self.name!r} failed to open: {self.failure}").to_message()
        return HttpResult(503, [("content-type", "application/json"), ("retry-after", "1")],
                          json.dumps(body).encode())

    async def http(self, method: str, path: str, query: str, headers: list[tuple[str, str]],
                   client: str = "127.0.0.1", root_path: str = "") -> HttpResult:
        """One HTTP request of the scene's API (``path`` without the ``/scenes/{name}`` prefix, which
        the gateway gives as ``root_path``)."""
        result = self._failed(path) if self.app is None else await http_request(
            self.app, method, path, query, headers, client, root_path)
        result.headers.append((REPLICA_HEADER, self.replica))
        return result

    async def probe(self, path: str) -> HttpResult:
        """GET ``path`` as the gateway itself (the scene's own token, whatever the client's): the
        health the gateway lists and the metrics the replica pushes."""
        headers = [("host", self._probe_host)]
        if self._token is not None:
            headers.append(("authorization", f"Bearer {self._token}"))
        return await self.http("GET", path, "", headers)

    async def stream(self, path: str, query: str, headers: list[tuple[str, str]],
                     messages: list[bytes | str], client: str = "127.0.0.1", mailbox=None,
                     session_id: str | None = None) -> AsyncIterator[WsMessage]:
        """A websocket session: ``messages`` (the client's so far) are sent in order, then those the
        gateway puts in ``mailbox`` under ``session_id`` as they come (see ``mailbox.py``); what the
        app sends is yielded until it closes, the mailbox closes the session, or the caller stops."""
        if self.app is None:
            body = protocol.ErrorBody(protocol.ErrorCode.NOT_READY,
                                      f"scene {self.name!r} failed to open: {self.failure}").to_message()
            yield WsMessage(bytes=protocol.pack(body))
            yield WsMessage(close=1013, reason="scene not ready")
            return
        session = WebSocketSession(self.app, path, query, headers, client).start()
        pull = None
        try:
            for message in messages:
                session.send(message)
            if mailbox is not None:
                pull = asyncio.create_task(_pull(mailbox, session_id, session))
            async for item in session.messages():
                yield item
        finally:
            if pull is not None:
                pull.cancel()
            await session.close()


async def _pull(mailbox, session_id: str, session: WebSocketSession) -> None:
    """Feed the session the client's messages from the gateway's mailbox until it closes the session
    (the client went away) or the mailbox is gone (the gateway died): then the app sees a disconnect."""
    try:
        while True:
            batch = await mailbox.get.remote(session_id)
            if batch is None:
                break
            for data in batch:
                session.send(data)
    except asyncio.CancelledError:
        raise
    except Exception as exc:  # the mailbox's actor died with its gateway
        log.warning("stream %s: its mailbox is gone (%s); ending the session", session_id,
                    type(exc).__name__)
    session.disconnect()


def probe_host(allowlist: list[str] | None) -> str:
    """The Host the gateway's own requests to a replica carry: one the scene answers to, so that a
    scene narrowing ``allowed_hosts`` still passes its probes (any name when it allows every one)."""
    if allowlist is None or "*" in allowlist or not allowlist:
        return "localhost"
    return allowlist[0]
