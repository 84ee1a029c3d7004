"""The gateway's mailbox of relayed websockets, as a plain object (the actor runs the same code)."""

from __future__ import annotations

import asyncio

import pytest

from edmcgs.server.ray_serve.mailbox import Mailbox


def test_messages_come_out_in_order_and_a_full_queue_refuses():
    async def main():
        box = Mailbox(max_pending=2)
        box.open("s")
        assert box.put("s", b"a") and box.put("s", "b")
        assert not box.put("s", b"c"), "a full queue refuses, never drops"
        assert await box.get("s") == [b"a", "b"]
        assert box.put("s", b"c")
        assert await box.get("s") == [b"c"]
        assert await box.get("s", wait_s=0.01) == [], "nothing pending: an empty batch, still open"

    asyncio.run(main())


def test_close_wakes_a_waiting_get_and_unknown_sessions_are_refused():
    async def main():
        box = Mailbox()
        box.open("s")
        waiting = asyncio.create_task(box.get("s", wait_s=10))
        await asyncio.sleep(0.01)
        box.close("s")
        assert await asyncio.wait_for(waiting, 1) is None
        assert await box.get("s") is None and not box.put("s", b"x")
        assert box.sessions() == 0
        with pytest.raises(ValueError, match="already open"):
            box.open("t")
            box.open("t")

    asyncio.run(main())


def test_a_sessions_queue_is_bounded_in_bytes_and_takes_one_message_of_any_size():
    async def main():
        box = Mailbox(max_pending=64, max_pending_bytes=2 << 20)
        box.open("s")
        mib = bytes(1 << 20)
        assert box.put("s", mib) and box.put("s", mib)
        assert not box.put("s", b"x"), "2 MiB pending: refused"
        assert await box.get("s") == [mib, mib]
        assert box.put("s", bytes(5 << 20)), "an empty queue takes one message, however large"
        assert not box.put("s", b"x")
        box.close("s")
        assert box.pending_bytes == {}

    asyncio.run(main())
