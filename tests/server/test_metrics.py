"""GET /metrics through prometheus-client: a registry per app (two apps in one process count apart), the
process and platform collectors on it, series read when scraped, an exposition Prometheus parses."""

from __future__ import annotations

import math

from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from edmcgs.server.app import create_app
from edmcgs.server.metrics import CONTENT_TYPE, Metrics
from edmcgs.server.settings import Settings
from harness.server import metric_values
from tests.support.stub import StubService


def _families(text: str) -> dict:
    return {f.name: f for f in text_string_to_metric_families(text)}


def test_two_apps_in_one_process_count_apart():
    apps = [create_app(Settings(), service_factory=StubService) for _ in range(2)]
    url = "http://127.0.0.1"
    with TestClient(apps[0], base_url=url) as a, TestClient(apps[1], base_url=url) as b:
        for _ in range(3):
            assert a.get("/healthz").status_code == 200
        assert b.get("/healthz").status_code == 200
        assert a.get("/render", params={"width": "wide"}).status_code == 422
        scraped = [c.get("/metrics") for c in (a, b)]
    for response in scraped:
        assert response.status_code == 200 and response.headers["content-type"] == CONTENT_TYPE
    first, second = (metric_values(r.text) for r in scraped)
    assert first['edmcgs_http_requests_total{code="200",route="/healthz"}'] == 3
    assert second['edmcgs_http_requests_total{code="200",route="/healthz"}'] == 1
    assert first['edmcgs_http_requests_total{code="422",route="/render"}'] == 1
    assert 'edmcgs_http_requests_total{code="422",route="/render"}' not in second
    assert first['edmcgs_http_request_duration_seconds_count{route="/healthz"}'] == 3


def test_the_exposition_parses_with_process_metrics_and_the_services_series():
    metrics = Metrics()
    metrics.requests.labels("/render", "200").inc(2)
    metrics.requests.labels('a"b\nc', "500").inc()
    for seconds in (0.004, 0.3, 7.0):
        metrics.render.labels("http").observe(seconds)
    metrics.readings.gauge("edmcgs_ring_fill_ratio", "Fill.", lambda: 0.25)
    metrics.readings.counter("edmcgs_events_dropped_total", "Dropped.", lambda: {"late": 3, "overflow": 0},
                             "reason")
    families = _families(metrics.exposition().decode())
    for name in ("process_cpu_seconds", "process_resident_memory_bytes", "process_start_time_seconds",
                 "python_info", "python_gc_collections"):
        assert name in families, name
    requests = {tuple(sorted(s.labels.items())): s.value for s in families["edmcgs_http_requests"].samples
                if s.name.endswith("_total")}
    assert requests == {(("code", "200"), ("route", "/render")): 2.0,
                        (("code", "500"), ("route", 'a"b\nc')): 1.0}  # label values escaped and read back
    assert families["edmcgs_http_requests"].type == "counter"
    render = {(s.name, s.labels.get("le")): s.value for s in families["edmcgs_render_seconds"].samples}
    assert render[("edmcgs_render_seconds_bucket", "0.005")] == 1
    assert render[("edmcgs_render_seconds_bucket", "0.5")] == 2
    assert render[("edmcgs_render_seconds_bucket", "+Inf")] == 3
    assert math.isclose(render[("edmcgs_render_seconds_sum", None)], 7.304)
    assert families["edmcgs_ring_fill_ratio"].samples[0].value == 0.25
    dropped = {s.labels["reason"]: s.value for s in families["edmcgs_events_dropped"].samples}
    assert families["edmcgs_events_dropped"].type == "counter" and dropped == {"late": 3, "overflow": 0}


def test_two_registries_never_share_a_series():
    first, second = Metrics(), Metrics()
    first.frames_sent.inc(5)
    assert metric_values(first.exposition().decode())["edmcgs_stream_frames_sent_total"] == 5
    assert metric_values(second.exposition().decode())["edmcgs_stream_frames_sent_total"] == 0
