"""The Serve application built from a config: one deployment per scene, behind the gateway.

    edmcgs-serve --ray scenes.yaml          # a local Ray, or the cluster at RAY_ADDRESS
    serve run edmcgs.server.ray_serve.app:app_builder config=scenes.yaml
"""

from __future__ import annotations

import logging
import os
import signal
import time
from pathlib import Path
from typing import Any

from pydantic import ValidationError
from ray import serve

from edmcgs.errors import InvalidInputError
from edmcgs.server.ray_serve.config import RayConfig, SceneConfig, load_config
from edmcgs.server.ray_serve.gateway import Gateway
from edmcgs.server.ray_serve.scene import SceneReplica

log = logging.getLogger("edmcgs.server.ray")

APP_NAME = "edmcgs"
HEALTH_CHECK_PERIOD_S = 2.0
"""Serve's probe of each replica: how soon a hung replica is replaced (a dead one is noticed at once)."""


def _check_settings(scene: SceneConfig, host: str) -> dict[str, Any]:
    """The scene's settings, validated here (the driver) so a typo fails before any replica starts.
    ``host``: where the proxy listens; as for edmcgs-serve, it decides the Host names a scene answers
    to when its settings name none (loopback: the loopback names; else any)."""
    from edmcgs.server.settings import Settings

    values = {**scene.settings_dict(), "host": host}
    try:
        settings = Settings(**values)
    except ValidationError as exc:
        lines = [f"{'.'.join(str(p) for p in e['loc']) or 'settings'}: {e['msg']}" for e in exc.errors()]
        raise InvalidInputError(f"scene {scene.name!r}: " + "; ".join(lines)) from None
    values["_concurrency"] = settings.render_workers + settings.render_queue + settings.max_streams
    values["_workers"] = settings.render_workers
    return values


def describe(scene: SceneConfig) -> dict[str, Any]:
    """What ``GET /scenes`` says of a scene besides its health."""
    if scene.demo:
        source = {"kind": "replay", "file": "bundled demo", "loop": True}
        checkpoint = "bundled demo"
    else:
        checkpoint = "learnt while serving (cold start)" if scene.cold else scene.checkpoint.name
        source = ({"kind": "live", "shared": True} | ({"replay": scene.replay.name} if scene.replay else {})
                  if scene.live else
                  {"kind": "replay", "file": scene.replay.name, "loop": scene.loop} if scene.replay else
                  {"kind": "none"})
    return {"name": scene.name, "checkpoint": checkpoint, "source": source, "replicas": scene.replicas}


def _ingest(scene: SceneConfig, values: dict[str, Any]):
    """A live scene's ingest deployment (``shared_source.py``), bound; None for the others."""
    if not scene.live:
        return None
    from edmcgs.server.ray_serve.shared_source import SceneIngest
    from edmcgs.server.settings import Settings

    batch_us = values.get("replay_batch_us", Settings.model_fields["replay_batch_us"].default)
    deployment = serve.deployment(SceneIngest).options(
        name=f"ingest-{scene.name}", num_replicas=1, ray_actor_options={"num_cpus": 0},
        max_ongoing_requests=10_000, health_check_period_s=HEALTH_CHECK_PERIOD_S)
    replay = None if scene.replay is None else str(scene.replay)
    return deployment.bind(scene.name, replay, scene.loop, batch_us)


def _learner(scene: SceneConfig, values: dict[str, Any], ingest):
    """A cold-start scene's learner deployment (``learner.py``: one, on a CPU of its own), bound; None
    for a scene with a checkpoint."""
    if not scene.cold:
        return None
    from edmcgs.server.ray_serve.learner import SAVE_TIMEOUT_S, SceneLearner

    deployment = serve.deployment(SceneLearner).options(
        name=f"learner-{scene.name}", num_replicas=1, ray_actor_options={"num_cpus": 1},
        max_ongoing_requests=1000, health_check_period_s=HEALTH_CHECK_PERIOD_S,
        graceful_shutdown_timeout_s=SAVE_TIMEOUT_S + 10)  # time to save what it learnt
    return deployment.bind(scene.name, values, ingest)


def build(config: RayConfig):
    """The application: the gateway (ingress) bound to one deployment per scene. ``EDMCGS_TOKEN`` (the
    environment where the application is built) guards the gateway's pages and every scene that sets no
    token of its own; the gateway's pages answer to the Host names a scene's would by default."""
    from edmcgs.server.settings import host_allowlist

    token = os.environ.get("EDMCGS_TOKEN") or None
    scenes, info = {}, {}
    for scene in config.scenes:
        if token is not None:
            scene.settings.setdefault("token", token)
        if config.http.allowed_hosts is not None:
            scene.settings.setdefault("allowed_hosts", config.http.allowed_hosts)
        values = _check_settings(scene, config.http.host)
        concurrency, workers = values.pop("_concurrency"), values.pop("_workers")
        if scene.max_replicas is not None and scene.max_replicas > scene.replicas:
            # More replicas while each holds more than its render workers' worth of calls.
            replicas = {"autoscaling_config": {"min_replicas": scene.replicas,
                                               "max_replicas": scene.max_replicas,
                                               "target_ongoing_requests": workers}}
        else:
            replicas = {"num_replicas": scene.replicas}
        deployment = serve.deployment(SceneReplica).options(
            name=f"scene-{scene.name}", **replicas,
            ray_actor_options={"num_cpus": scene.cpus_per_replica},
            # Each open stream holds a call for its life; renders past the pool's queue get its 503.
            max_ongoing_requests=concurrency, max_queued_requests=scene.max_queued,
            health_check_period_s=HEALTH_CHECK_PERIOD_S, graceful_shutdown_timeout_s=5)
        ingest = _ingest(scene, values)
        scenes[scene.name] = deployment.bind(scene.name, values, ingest, _learner(scene, values, ingest))
        info[scene.name] = describe(scene)
    gateway = serve.deployment(Gateway).options(name="gateway", num_replicas=1,
                                                ray_actor_options={"num_cpus": 0},
                                                max_ongoing_requests=1000)
    return gateway.bind(scenes, info, token, host_allowlist(config.http.host, config.http.allowed_hosts))


def app_builder(args: dict[str, str]):
    """``serve run edmcgs.server.ray_serve.app:app_builder config=PATH``."""
    if "config" not in args:
        raise InvalidInputError("give the scenes' YAML: serve run ...:app_builder config=PATH")
    return build(load_config(args["config"]))


def start(config: RayConfig, *, name: str = APP_NAME) -> None:
    """Start Serve's proxy where the config says and run the application (Ray must be initialised);
    returns once every scene's replicas are up."""
    serve.start(http_options={"host": config.http.host, "port": config.http.port})
    serve.run(build(config), name=name, route_prefix="/")


def _interrupt(*_args) -> None:
    raise KeyboardInterrupt


def main(config_path: str | Path, *, num_cpus: int | None = None) -> int:
    """``edmcgs-serve --ray CONFIG``: serve until Ctrl-C, then shut Serve (and a Ray started here) down."""
    import ray

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    config = load_config(config_path)
    joined = bool(os.environ.get("RAY_ADDRESS"))
    ray.init(num_cpus=None if joined else num_cpus, include_dashboard=False)
    # After ray.init, which sets its own: SIGTERM (a container's stop) ends as Ctrl-C does, Serve and
    # the Ray started here shut down.
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        start(config)
        log.info("serving %d scene(s) on http://%s:%d/scenes", len(config.scenes), config.http.host,
                 config.http.port)
        print(f"edmcgs-serve --ray: {', '.join(s.name for s in config.scenes)} on "
              f"http://{config.http.host}:{config.http.port}/scenes", flush=True)
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 130
    finally:
        serve.shutdown()
        if not joined:
            ray.shutdown()
