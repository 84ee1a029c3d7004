"""The service's Prometheus metrics, through prometheus-client.

Each app has a registry of its own (``Metrics.registry``), never the library's global default one: two
apps in one process (tests, an embedding program) keep separate counts. The registry also carries the
process and platform collectors (CPU seconds, resident memory, open files, start time, Python version).

Series kept elsewhere (the ring's counts, the render pool's queue, the online anchors) are read when
scraped (``Readings``), so they are never stale and cost nothing between scrapes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from prometheus_client import (
    CONTENT_TYPE_PLAIN_0_0_4,
    CollectorRegistry,
    Counter,
    GCCollector,
    Histogram,
    PlatformCollector,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

LATENCY_BUCKETS_S = (0.005, 0.01, 0.015, 0.025, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5, 5.0)
STAGE_BUCKETS_S = (0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.015, 0.025, 0.05, 0.1, 0.5)
CONTENT_TYPE = CONTENT_TYPE_PLAIN_0_0_4
"""The exposition's media type: the Prometheus text format 0.0.4 that ``generate_latest`` writes."""

Read = Callable[[], float | dict[str, float]]


class Readings:
    """A collector of series read from callbacks when scraped: ``read()`` returns a number, or with a
    ``label`` a map {label value: number}."""

    def __init__(self):
        self._series: list[tuple[type[Metric], str, str, Read, str | None]] = []

    def gauge(self, name: str, help_text: str, read: Read, label: str | None = None) -> None:
        self._series.append((GaugeMetricFamily, name, help_text, read, label))

    def counter(self, name: str, help_text: str, read: Read, label: str | None = None) -> None:
        """A count kept elsewhere; ``name`` ends with ``_total``."""
        self._series.append((CounterMetricFamily, name, help_text, read, label))

    def collect(self) -> Iterator[Metric]:
        for family_type, name, help_text, read, label in self._series:
            value = read()
            family = family_type(name, help_text, labels=[label] if label else None)
            if label:
                for key, v in sorted(value.items()):
                    family.add_metric([key], float(v))
            else:
                family.add_metric([], float(value))
            yield family


class Metrics:
    """The series of one service (``GET /metrics``); ``readings`` takes the ones read when scraped."""

    def __init__(self):
        self.registry = registry = CollectorRegistry()
        for collector in (ProcessCollector, PlatformCollector, GCCollector):
            collector(registry=registry)
        self.requests = Counter("edmcgs_http_requests_total", "HTTP requests by route and status code.",
                                ("route", "code"), registry=registry)
        self.latency = Histogram("edmcgs_http_request_duration_seconds", "HTTP request latency by route "
                                 "(seconds).", ("route",), buckets=LATENCY_BUCKETS_S, registry=registry)
        self.render = Histogram("edmcgs_render_seconds", "Render + encode time by path (seconds).",
                                ("path",), buckets=LATENCY_BUCKETS_S, registry=registry)
        self.render_stage = Histogram(
            "edmcgs_render_stage_seconds", "Where a render's time goes (seconds): state (the window's events "
            "and the deformation, or a cache hit), raster (the rasterizer and uint8), project (onto the "
            "events since an online anchor's frame, the event camera's view past the span; then uint8 is "
            "here), encode (PNG/JPEG/raw).",
            ("stage",), buckets=STAGE_BUCKETS_S, registry=registry)
        self.frames_sent = Counter("edmcgs_stream_frames_sent_total", "Websocket frames sent.",
                                   registry=registry)
        self.frames_dropped = Counter("edmcgs_stream_frames_dropped_total",
                                      "Websocket frames dropped because the client read slower than they "
                                      "were rendered (latest wins).", registry=registry)
        self.fit = Histogram("edmcgs_online_fit_seconds", "Time of one online anchor's correction (seconds).",
                             buckets=LATENCY_BUCKETS_S, registry=registry)
        self.fit_loss = Histogram("edmcgs_online_fit_loss_l1", "L1 photometric loss of each online anchor "
                                  "after its correction.", buckets=(0.01, 0.02, 0.05, 0.1, 0.2, 0.5),
                                  registry=registry)
        self.readings = Readings()
        registry.register(self.readings)
        self.stream_clients = 0
        self.streams_refused = 0

    def exposition(self) -> bytes:
        """The body of ``GET /metrics``."""
        return generate_latest(self.registry)
