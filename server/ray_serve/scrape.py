"""A scene's metrics across its replicas: each replica pushes its Prometheus exposition to the gateway's
board every ``PUSH_PERIOD_S``; ``/scenes/{name}/metrics`` answers every live replica's series, each
labelled ``replica``, one family at a time, and the gateway's own counters of the scene after them.

Pushed rather than asked for: a Serve handle reaches *a* replica, never each one. A replica that stops
pushing for ``STALE_S`` (killed, its node lost) leaves the board and counts as lost.
"""

from __future__ import annotations

import re
import time

PUSH_PERIOD_S = 1.0
STALE_S = 10.0
"""A replica silent this long is taken as gone."""
BOARD_NAME = "edmcgs-metrics-{app}"
"""The board actor's name in Serve's namespace (one per application, owned by its gateway)."""
SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(.*)\})?(\s.*)$")


class MetricsBoard:
    """Plain class; the gateway wraps it with ``ray.remote``. The latest exposition of each replica."""

    def __init__(self):
        self.latest: dict[str, dict[str, tuple[float, str]]] = {}  # scene -> replica -> (monotonic, text)
        self.lost: dict[str, int] = {}

    def push(self, scene: str, replica: str, text: str) -> None:
        self.latest.setdefault(scene, {})[replica] = (time.monotonic(), text)

    def scene(self, scene: str) -> tuple[dict[str, str], int]:
        """``(replica -> exposition, replicas lost so far)`` of the scene's live replicas."""
        now = time.monotonic()
        by_replica = self.latest.get(scene, {})
        for replica in [r for r, (at, _) in by_replica.items() if now - at > STALE_S]:
            del by_replica[replica]
            self.lost[scene] = self.lost.get(scene, 0) + 1
        return {r: text for r, (_, text) in by_replica.items()}, self.lost.get(scene, 0)


def _labelled(line: str, label: str) -> str:
    match = SAMPLE.match(line)
    if match is None:
        return line
    name, _, labels, rest = match.groups()
    return f"{name}{{{label}{',' + labels if labels else ''}}}{rest}"


def merge(expositions: dict[str, str], label: str = "replica") -> str:
    """One exposition from several: each family's ``# HELP``/``# TYPE`` once, then its samples from
    every source, each with ``label="<source>"`` added."""
    families: dict[str, tuple[list[str], list[str]]] = {}
    for source, text in sorted(expositions.items()):
        escaped = source.replace("\\", "\\\\").replace('"', '\\"')
        tag = f'{label}="{escaped}"'
        family = ""
        for line in text.splitlines():
            if not line.strip():
                continue
            if line.startswith("#"):
                parts = line.split(None, 3)
                if len(parts) >= 3 and parts[1] in ("HELP", "TYPE"):
                    family = parts[2]
                    head, _ = families.setdefault(family, ([], []))
                    if line not in head:
                        head.append(line)
                continue
            families.setdefault(family, ([], []))[1].append(_labelled(line, tag))
    out = [line for head, samples in families.values() for line in (*head, *samples)]
    return "\n".join(out) + "\n"


def gateway_series(scene: str, *, retries: int, stream_restarts: int, replicas: int, lost: int) -> str:
    """The gateway's counters of one scene, as exposition text."""
    tag = f'scene="{scene}"'
    rows = [("edmcgs_gateway_retries_total", "counter", "Calls sent again after their replica died.",
             retries),
            ("edmcgs_gateway_stream_restarts_total", "counter",
             "Websocket sessions started again on another replica after theirs died.", stream_restarts),
            ("edmcgs_gateway_replicas_lost_total", "counter",
             f"Replicas that stopped reporting their metrics for {STALE_S:g} s (died).", lost),
            ("edmcgs_gateway_replicas_reporting", "gauge", "Replicas whose metrics are in this answer.",
             replicas)]
    return "".join(f"# HELP {n} {h}\n# TYPE {n} {t}\n{n}{{{tag}}} {v}\n" for n, t, h, v in rows)
