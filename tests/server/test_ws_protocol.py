"""The websocket protocol ``edmcgs-serve`` runs (``connections.DroppingWebSocketProtocol``), driven byte
by byte from websockets' own client protocol: a compressed message just under the size limit that
decompresses above it is closed with 1009, and the app's next send is a disconnect, not a RuntimeError
(which the stream route logged as its own failure)."""

from __future__ import annotations

import asyncio
import os

import uvicorn
from uvicorn.server import ServerState
from websockets.client import ClientProtocol
from websockets.extensions.permessage_deflate import ClientPerMessageDeflateFactory
from websockets.uri import parse_uri

from edmcgs.server.connections import WS_MAX_BYTES, DroppingWebSocketProtocol


class Transport(asyncio.Transport):
    def __init__(self):
        super().__init__()
        self.out, self.closing = bytearray(), False

    def write(self, data):
        self.out += data

    def close(self):
        self.closing = True

    def abort(self):
        self.closing = True

    def is_closing(self):
        return self.closing

    def pause_reading(self):
        pass

    def resume_reading(self):
        pass

    def get_extra_info(self, name, default=None):
        return {"peername": ("127.0.0.1", 5), "sockname": ("127.0.0.1", 80)}.get(name, default)


def test_a_compressed_message_over_the_limit_is_closed_1009_and_the_app_sees_a_disconnect():
    sent_after_close: list[BaseException] = []
    app_sending = asyncio.Event()

    async def app(scope, receive, send):  # a stream: accept, then frames until something stops it
        await receive()
        await send({"type": "websocket.accept"})
        app_sending.set()
        try:
            while True:
                await send({"type": "websocket.send", "bytes": b"frame"})
                await asyncio.sleep(0.01)
        except BaseException as exc:
            sent_after_close.append(exc)

    async def main():
        config = uvicorn.Config(app, ws_max_size=WS_MAX_BYTES, lifespan="off", log_config=None)
        config.load()
        server = DroppingWebSocketProtocol(config, ServerState(), {}, _loop=asyncio.get_running_loop())
        transport = Transport()
        server.connection_made(transport)
        client = ClientProtocol(parse_uri("ws://127.0.0.1/stream"), max_size=None,
                                extensions=[ClientPerMessageDeflateFactory()])
        client.send_request(client.connect())
        server.data_received(b"".join(client.data_to_send()))
        await asyncio.wait_for(app_sending.wait(), 5)
        client.receive_data(bytes(transport.out))  # the 101 and the first frames
        transport.out.clear()
        # Random bytes barely compress: just under the limit on the wire, over it once decompressed.
        client.send_binary(os.urandom(WS_MAX_BYTES - 200_000) + bytes(400_000))
        wire = b"".join(client.data_to_send())
        assert len(wire) < WS_MAX_BYTES
        server.data_received(wire)
        await asyncio.sleep(0.1)
        client.receive_data(bytes(transport.out))
        assert client.close_rcvd is not None and client.close_rcvd.code == 1009
        assert len(sent_after_close) == 1 and isinstance(sent_after_close[0], OSError), sent_after_close

    asyncio.run(main())


def test_a_plain_message_over_the_limit_is_closed_1009():
    async def app(scope, receive, send):
        await receive()
        await send({"type": "websocket.accept"})
        await receive()

    async def main():
        config = uvicorn.Config(app, ws_max_size=WS_MAX_BYTES, lifespan="off", log_config=None)
        config.load()
        server = DroppingWebSocketProtocol(config, ServerState(), {}, _loop=asyncio.get_running_loop())
        transport = Transport()
        server.connection_made(transport)
        client = ClientProtocol(parse_uri("ws://127.0.0.1/stream"), max_size=None)
        client.send_request(client.connect())
        server.data_received(b"".join(client.data_to_send()))
        await asyncio.sleep(0.05)
        client.receive_data(bytes(transport.out))
        transport.out.clear()
        client.send_binary(bytes(WS_MAX_BYTES + 1))
        server.data_received(b"".join(client.data_to_send()))
        client.receive_data(bytes(transport.out))
        assert client.close_rcvd is not None and client.close_rcvd.code == 1009

    asyncio.run(main())
