"""A service stub for app-level tests: what the routes, the middleware and the docs touch before a render
(settings, metrics, the render pool, the head signal), with no model, source or render behind it."""

from __future__ import annotations

import asyncio
import types


class StubService:
    """What the routes and middleware touch before a render; renders are never reached here."""

    def __init__(self, settings):
        from edmcgs.server.render_pool import RenderPool
        from edmcgs.server.service import Metrics

        self.settings = settings
        self.metrics = Metrics()
        self.pool = RenderPool(settings.render_workers, settings.render_queue)
        self.signal = types.SimpleNamespace(wait=lambda timeout: asyncio.sleep(timeout))
        t0 = 1_600_000_000_000_000
        self.engine = types.SimpleNamespace(
            head=lambda: None, first_us=t0, end_us=t0 + 2_000_000,
            t_us_of_seconds=lambda t: t0 + round(t * 1e6), seconds_of=lambda t_us: (t_us - t0) / 1e6)

    def start(self, loop):
        pass

    def close(self):
        self.pool.close()

    def health(self):
        return True, {"ready": True}

    def size(self, width, height):
        return 8, 8

    frame_bytes = 64 * 1024
    """Size of each stub frame (incompressible)."""

    def render_frame(self, t_us, pose, width, height, fmt, mode="rgb"):
        """A frame of ``frame_bytes`` random bytes, counted in ``renders``: a stream's own path (the pool,
        the producer, the sender) with no model behind it."""
        import os

        from edmcgs import protocol
        from edmcgs.server.service import RenderedFrame

        self.renders = getattr(self, "renders", 0) + 1
        t_us = self.engine.first_us if t_us is None else t_us
        meta = protocol.FrameMeta(t_us=t_us, t=self.engine.seconds_of(t_us), anchor_us=self.engine.first_us,
                                  events=0, render_ms=0.1, width=width, height=height, channels=3, format=fmt,
                                  anchor="checkpoint", projected=False)
        return RenderedFrame(meta, os.urandom(self.frame_bytes), (t_us - 1000, t_us))
