"""A local Ray with the scenes' Serve application, for the Ray tests and ``bench.ray_serve``.

Small on purpose (the machine has 2 cores): ``ray.init(num_cpus=2)``, no dashboard, and everything shut
down on exit so no Ray process outlives the test or benchmark.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx

from harness.server import free_port


def scene_entry(name: str, checkpoint: Path | None, replay: Path | None, *, replicas: int = 1,
                **settings) -> dict:
    """One ``scenes`` item of the YAML (as parsed); ``checkpoint=None``: the bundled demo."""
    entry: dict = {"name": name, "replicas": replicas, "cpus_per_replica": 0.25, "loop": True,
                   "settings": {"raster_threads": 1, **settings}}
    if checkpoint is None:
        entry = {**entry, "demo": True}
        entry.pop("loop")
    else:
        entry["checkpoint"] = str(checkpoint)
        if replay is not None:
            entry["replay"] = str(replay)
    return entry


class LocalServe:
    """``with LocalServe(scenes) as serve_: httpx.get(serve_.url + "/scenes")``; ``startup_s``: from
    ``ray.init`` to every replica up."""

    def __init__(self, scenes: list[dict], *, num_cpus: int = 2, base: Path | None = None):
        from edmcgs.server.ray_serve.config import parse_config

        self.port = free_port()
        self.config = parse_config({"http": {"host": "127.0.0.1", "port": self.port}, "scenes": scenes},
                                   base=base or Path.cwd())
        self.num_cpus = num_cpus
        self.url = f"http://127.0.0.1:{self.port}"
        self.startup_s = float("nan")
        self.ray_init_s = float("nan")

    def __enter__(self) -> LocalServe:
        import ray

        from edmcgs.server.ray_serve.app import start

        t0 = time.perf_counter()
        ray.init(num_cpus=self.num_cpus, include_dashboard=False, log_to_driver=False)
        self.ray_init_s = time.perf_counter() - t0
        try:
            start(self.config)
        except BaseException:
            self._shutdown()
            raise
        self.startup_s = time.perf_counter() - t0
        return self

    def __exit__(self, *exc) -> None:
        self._shutdown()

    @staticmethod
    def _shutdown() -> None:
        import ray
        from ray import serve

        try:
            serve.shutdown()
        finally:
            ray.shutdown()

    def wait_renderable(self, name: str, timeout: float = 60.0, token: str | None = None) -> dict:
        """The scene's GET /scene once its replay covers the whole span (every replica's ring fills as
        its own replay plays)."""
        deadline = time.monotonic() + timeout
        while True:
            headers = {"Authorization": f"Bearer {token}"} if token else None
            scene = httpx.get(f"{self.url}/scenes/{name}/scene", headers=headers, timeout=30).json()
            r = scene.get("renderable")
            if r and r["t_us_max"] >= scene["t_end_us"] - 20_000:
                return scene
            if time.monotonic() > deadline:
                raise TimeoutError(f"scene {name!r} is not renderable after {timeout} s: {scene}")
            time.sleep(0.2)

    @staticmethod
    def kill_replica(actor_name: str) -> None:
        """Kill one replica's actor (a crash: no graceful shutdown); Serve starts a replacement."""
        import ray

        ray.kill(ray.get_actor(actor_name, namespace="serve"), no_restart=True)

    @staticmethod
    def replica_actors(deployment: str, app: str = "edmcgs") -> list[str]:
        """The actor names of a deployment's replicas (``SERVE_REPLICA::app#deployment#id``)."""
        import ray

        prefix = f"SERVE_REPLICA::{app}#{deployment}#"
        return sorted(a["name"] for a in ray.util.list_named_actors(all_namespaces=True)
                      if a["name"].startswith(prefix))

    @staticmethod
    def running_replicas(deployment: str, app: str = "edmcgs") -> int:
        from ray import serve

        status = serve.status().applications[app].deployments[deployment]
        states = {getattr(k, "value", str(k)): v for k, v in status.replica_states.items()}
        return int(states.get("RUNNING", 0))
