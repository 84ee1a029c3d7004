"""A relayed websocket (``relay.StreamRelay``) bounded in bytes at every step, with the gateway's real
mailbox and stand-ins for the websocket and the replica (no Ray started): a message over 1 MiB is
refused with 1009 before it goes anywhere, a client sending faster than the scene takes its messages is
closed with 1008, and the history a restarted session replays keeps the newest messages within its
bytes, skipping exactly the replies the client already had."""

from __future__ import annotations

import asyncio
import types

import pytest

pytest.importorskip("ray.serve", reason="the 'ray' extra is not installed")

from edmcgs import protocol
from edmcgs.server.connections import WS_MAX_BYTES
from edmcgs.server.ray_serve.mailbox import Mailbox
from edmcgs.server.ray_serve.relay import HISTORY_BYTES, History, StreamRelay
from edmcgs.server.ray_serve.retry import Retrier

MIB = 1 << 20


class Remote:
    """``actor.method.remote(...)`` for a plain object's method: an awaitable of its result."""

    def __init__(self, target):
        self.target = target

    def __getattr__(self, name):
        method = getattr(self.target, name)

        async def call(*args):
            result = method(*args)
            return await result if asyncio.iscoroutine(result) else result

        return types.SimpleNamespace(remote=call)


class Client:
    """The gateway's side of a client's websocket: ``messages`` arrive, then the client waits."""

    def __init__(self, messages):
        self.incoming = list(messages)
        self.closed: tuple[int, str] | None = None
        self.sent: list[dict] = []
        self.url = types.SimpleNamespace(query="")
        self.headers = {}

    async def receive(self):
        if self.incoming:
            data = self.incoming.pop(0)
            return {"type": "websocket.receive", "bytes": data}
        await asyncio.Event().wait()

    async def close(self, code=1000, reason=""):
        self.closed = (code, reason)

    async def send_bytes(self, data):
        self.sent.append(protocol.unpack(data))


class Replica:
    """A scene replica whose session never sends nor pulls its mailbox: the slowest scene."""

    def options(self, **_):
        return self

    @property
    def stream(self):
        return types.SimpleNamespace(remote=lambda *args: Session())


class Session:
    def __aiter__(self):
        return self

    async def __anext__(self):
        await asyncio.Event().wait()

    def cancel(self):
        pass


def _relay(messages) -> tuple[StreamRelay, Client, Mailbox]:
    client, mailbox = Client(messages), Mailbox()
    return StreamRelay(client, Replica(), Retrier(), "127.0.0.1", Remote(mailbox)), client, mailbox


def test_a_message_over_the_limit_is_refused_with_1009_before_it_goes_anywhere():
    async def main():
        relay, client, mailbox = _relay([b"{}", bytes(16 * MIB)])
        await asyncio.wait_for(relay.run(), 5)
        assert client.closed[0] == 1009 and str(WS_MAX_BYTES) in client.closed[1]
        assert list(relay.history.messages) == [b"{}"] and mailbox.sessions() == 0

    asyncio.run(main())


def test_a_message_longer_than_any_subscription_is_answered_at_the_gateway_and_goes_no_further():
    async def main():
        relay, client, mailbox = _relay([bytes(MIB)] * 3)
        run = asyncio.create_task(relay.run())
        await asyncio.sleep(0.2)
        assert [m["error"] for m in client.sent] == ["invalid_input"] * 3 and client.closed is None
        assert "longer than" in client.sent[0]["detail"]
        assert relay.history.sent == 0 and mailbox.pending_bytes == {relay.session: 0}
        run.cancel()

    asyncio.run(main())


def test_a_client_sending_faster_than_the_scene_takes_is_closed_with_1008():
    async def main():
        size = protocol.MAX_MESSAGE_BYTES
        relay, client, _ = _relay([bytes(size)] * 1000)
        await asyncio.wait_for(relay.run(), 5)
        assert client.closed[0] == 1008, client.closed
        assert len(client.incoming) > 900, "it stopped reading at once"
        assert relay.history.bytes <= HISTORY_BYTES + size and relay.inbox_bytes <= 4 * MIB

    asyncio.run(main())


def test_the_history_keeps_the_newest_within_its_bytes_and_counts_the_replies_had():
    history = History(max_messages=4, max_bytes=100)
    for k in range(10):
        history.add(bytes([k]) * 30)
    assert [m[0] for m in history.messages] == [7, 8, 9] and history.bytes == 90 and history.sent == 10
    assert history.answered(10) == 3 and history.answered(8) == 1 and history.answered(5) == 0
    history.add(b"x" * 500)  # larger than the bound alone: kept, as the newest
    assert list(history.messages) == [b"x" * 500] and history.answered(10) == 0
