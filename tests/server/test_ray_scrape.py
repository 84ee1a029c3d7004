"""Merging replicas' Prometheus expositions (no Ray needed)."""

from __future__ import annotations

from edmcgs.server.ray_serve.scrape import gateway_series, merge

ONE = """# HELP edmcgs_http_requests_total HTTP requests.
# TYPE edmcgs_http_requests_total counter
edmcgs_http_requests_total{route="/render",status="200"} 3.0
# HELP up Whether up.
# TYPE up gauge
up 1.0
"""


def test_each_family_once_with_every_replicas_samples_labelled():
    text = merge({"r1": ONE, "r2": ONE.replace("3.0", "5.0")})
    lines = text.splitlines()
    assert lines.count("# TYPE edmcgs_http_requests_total counter") == 1
    i = lines.index("# TYPE edmcgs_http_requests_total counter")
    assert lines[i + 1:i + 3] == [
        'edmcgs_http_requests_total{replica="r1",route="/render",status="200"} 3.0',
        'edmcgs_http_requests_total{replica="r2",route="/render",status="200"} 5.0']
    assert 'up{replica="r1"} 1.0' in lines and 'up{replica="r2"} 1.0' in lines
    assert lines.index("# TYPE up gauge") > i + 2, "a family's samples stay together"


def test_gateway_series_are_valid_exposition():
    text = gateway_series("beta", retries=2, stream_restarts=1, replicas=2, lost=0)
    assert 'edmcgs_gateway_retries_total{scene="beta"} 2' in text
    assert 'edmcgs_gateway_replicas_reporting{scene="beta"} 2' in text
    assert merge({"x": text}).count("# TYPE") == 4
