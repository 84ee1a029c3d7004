"""bench.serve's one-client measurement when the replay overtakes the span it was told: a fast replay of a
busy recording makes the ring forget the oldest events, so an instant from the first span can be gone."""

from __future__ import annotations

from types import SimpleNamespace

from bench.serve import measure_single
from edmcgs.clients.client import TimeUnavailable


class ForgetfulClient:
    """A service whose ring keeps t >= ``kept_from`` only, moving on by 50 ms every request."""

    def __init__(self):
        self.kept_from, self.asked, self.scenes = 1_000_000, [], 0

    def render(self, *, t_us, width, height, format):
        self.asked.append(t_us)
        self.kept_from += 50_000
        if t_us < self.kept_from:
            raise TimeUnavailable(416, "gone", error="time_unavailable")
        return b"", SimpleNamespace(render_ms=1.0, events=10)

    def scene(self):
        self.scenes += 1
        return {"renderable": {"t_us_min": self.kept_from, "t_us_max": self.kept_from + 10_000_000}}


def test_an_instant_the_ring_forgot_is_counted_apart_and_the_span_read_again():
    client = ForgetfulClient()
    out = measure_single(client, {"renderable": {"t_us_min": 0, "t_us_max": 2_000_000}}, 0.2, (8, 6))
    assert out["render_refused_1_client"] >= 1
    assert client.scenes == out["render_refused_1_client"]
    assert out["render_requests_1_client"] >= 1  # later instants, from the span read again, are timed
    assert out["render_requests_1_client"] + out["render_refused_1_client"] == len(client.asked)
