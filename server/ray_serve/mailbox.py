"""Client messages of relayed websockets, on their way from the gateway into running replica sessions.

A streaming Ray call takes no input once started, so the gateway cannot hand a replica's session a
message through the call itself. It puts each message here under the session's id instead, and the
replica's session pulls them (``get`` waits for the next ones). One mailbox actor serves the gateway's
connections; it belongs to the gateway, so it goes away with it, and a replica whose mailbox is gone
ends its sessions.

Each session's queue is bounded in messages and in bytes: a ``put`` on a full queue is refused
(``False``), never dropped silently, and the gateway closes that connection. ``close`` ends a session's
queue: the replica's ``get`` answers ``None`` and its session ends; a ``get`` on an id never opened, or
already closed, answers ``None`` too.
"""

from __future__ import annotations

import asyncio

MAX_PENDING = 64
"""Messages of one session the replica has not pulled yet before the mailbox refuses more."""
MAX_PENDING_BYTES = 2 << 20
"""Their bytes at most (one message of any size is always taken by an empty queue)."""
GET_WAIT_S = 5.0
"""Longest a ``get`` waits before answering an empty list (the replica asks again)."""


class Mailbox:
    """Plain class; the gateway wraps it with ``ray.remote`` (an async actor: ``get`` waits)."""

    def __init__(self, max_pending: int = MAX_PENDING, max_pending_bytes: int = MAX_PENDING_BYTES):
        self.max_pending, self.max_pending_bytes = max_pending, max_pending_bytes
        self.queues: dict[str, asyncio.Queue] = {}
        self.pending_bytes: dict[str, int] = {}

    def open(self, session: str) -> None:
        if session in self.queues:
            raise ValueError(f"session {session!r} is already open")
        self.queues[session] = asyncio.Queue(maxsize=self.max_pending)
        self.pending_bytes[session] = 0

    def put(self, session: str, data: bytes | str) -> bool:
        """Queue a client message; False when the session is unknown or its queue is full."""
        queue = self.queues.get(session)
        if queue is None or queue.full():
            return False
        held = self.pending_bytes[session]
        if held and held + len(data) > self.max_pending_bytes:
            return False
        queue.put_nowait(data)
        self.pending_bytes[session] = held + len(data)
        return True

    async def get(self, session: str, wait_s: float = GET_WAIT_S) -> list[bytes | str] | None:
        """The session's pending messages in order (waiting for the first up to ``wait_s``: an empty
        list then), or ``None`` once the session is closed."""
        queue = self.queues.get(session)
        if queue is None:
            return None
        try:
            first = await asyncio.wait_for(queue.get(), wait_s)
        except TimeoutError:
            return [] if session in self.queues else None
        out = [first]
        while not queue.empty():
            out.append(queue.get_nowait())
        if None in out:  # closed meanwhile
            return None
        self.pending_bytes[session] = 0
        return out

    def close(self, session: str) -> None:
        """End the session: a waiting ``get`` answers ``None`` (the sentinel wakes it)."""
        queue = self.queues.pop(session, None)
        self.pending_bytes.pop(session, None)
        if queue is not None:
            while not queue.empty():
                queue.get_nowait()
            queue.put_nowait(None)

    def sessions(self) -> int:
        return len(self.queues)
