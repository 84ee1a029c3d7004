"""Prometheus metrics in the text exposition format (version 0.0.4).

A few lines of our own rather than prometheus-client: the service has a dozen series, one process,
and no need for its global default registry (which would leak state between apps in one process).
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable, Iterable

LATENCY_BUCKETS_S = (0.005, 0.01, 0.015, 0.025, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5, 5.0)


def _labels(names: tuple[str, ...], values: tuple[str, ...], extra: str = "") -> str:
    parts = [f'{n}="{_escape(v)}"' for n, v in zip(names, values, strict=True)]
    if extra:
        parts.append(extra)
    return "{" + ",".join(parts) + "}" if parts else ""


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _num(v: float) -> str:
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    return repr(float(v)) if not float(v).is_integer() else str(int(v))


class _Metric:
    kind = ""

    def __init__(self, name: str, help_text: str, labels: tuple[str, ...] = ()):
        self.name, self.help, self.label_names = name, help_text, labels
        self._lock = threading.Lock()

    def header(self) -> list[str]:
        return [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} {self.kind}"]


class Counter(_Metric):
    """A monotonically increasing count, optionally per label values."""

    kind = "counter"

    def __init__(self, name: str, help_text: str, labels: tuple[str, ...] = ()):
        super().__init__(name, help_text, labels)
        self._values: dict[tuple[str, ...], float] = {} if labels else {(): 0.0}

    def inc(self, amount: float = 1.0, *labels: str) -> None:
        with self._lock:
            self._values[labels] = self._values.get(labels, 0.0) + amount

    def value(self, *labels: str) -> float:
        with self._lock:
            return self._values.get(labels, 0.0)

    def lines(self) -> list[str]:
        with self._lock:
            items = sorted(self._values.items())
        return [*self.header(),
                *(f"{self.name}{_labels(self.label_names, k)} {_num(v)}" for k, v in items)]


class Gauge(_Metric):
    """A value read when scraped (from a callback), so it is never stale.

    ``read()`` returns a number, or with ``label`` a map {label value: number}.
    """

    kind = "gauge"

    def __init__(self, name: str, help_text: str, read: Callable[[], float | dict[str, float]],
                 label: str | None = None):
        super().__init__(name, help_text, (label,) if label else ())
        self._read = read

    def lines(self) -> list[str]:
        value = self._read()
        if not self.label_names:
            return [*self.header(), f"{self.name} {_num(value)}"]
        return [*self.header(), *(f"{self.name}{_labels(self.label_names, (k,))} {_num(v)}"
                                  for k, v in sorted(value.items()))]


class CallbackCounter(Gauge):
    """A counter kept elsewhere (e.g. the ring buffer's), read when scraped."""

    kind = "counter"


class Histogram(_Metric):
    """Cumulative buckets, sum and count, optionally per label values."""

    kind = "histogram"

    def __init__(self, name: str, help_text: str, labels: tuple[str, ...] = (),
                 buckets: Iterable[float] = LATENCY_BUCKETS_S):
        super().__init__(name, help_text, labels)
        self.buckets = tuple(sorted(buckets))
        self._series: dict[tuple[str, ...], list] = {}  # labels -> [counts per bucket + inf, sum]

    def observe(self, value: float, *labels: str) -> None:
        i = bisect.bisect_left(self.buckets, value)
        with self._lock:
            series = self._series.setdefault(labels, [[0] * (len(self.buckets) + 1), 0.0])
            series[0][i] += 1
            series[1] += value

    def count(self, *labels: str) -> int:
        with self._lock:
            series = self._series.get(labels)
            return sum(series[0]) if series else 0

    def lines(self) -> list[str]:
        out = self.header()
        with self._lock:
            items = sorted((k, (list(v[0]), v[1])) for k, v in self._series.items())
        for key, (counts, total) in items:
            cumulative = 0
            for bound, c in zip((*self.buckets, math.inf), counts, strict=True):
                cumulative += c
                le = f'le="{_num(bound)}"'
                out.append(f"{self.name}_bucket{_labels(self.label_names, key, le)} {cumulative}")
            out.append(f"{self.name}_sum{_labels(self.label_names, key)} {_num(total)}")
            out.append(f"{self.name}_count{_labels(self.label_names, key)} {cumulative}")
        return out


class Registry:
    """The metrics of one app; ``render()`` is the body of ``GET /metrics``."""

    CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

    def __init__(self):
        self._metrics: list[_Metric] = []

    def add(self, metric: _Metric) -> _Metric:
        self._metrics.append(metric)
        return metric

    def render(self) -> str:
        return "\n".join(line for m in self._metrics for line in m.lines()) + "\n"
