"""The Ray layer's parts that need no running Ray: the scenes' YAML, the in-process ASGI drivers, the
retry rule, and the default server's independence from Ray."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi import FastAPI, WebSocket

from edmcgs.errors import InvalidInputError
from edmcgs.server.ray_serve.asgi import WebSocketSession, http_request
from edmcgs.server.ray_serve.config import load_config, parse_config


@pytest.fixture
def files(tmp_path) -> Path:
    (tmp_path / "s.ckpt").write_bytes(b"x")
    (tmp_path / "s.h5").write_bytes(b"x")
    return tmp_path


def scene(**kw) -> dict:
    return {"name": "street", "checkpoint": "s.ckpt", "replay": "s.h5", **kw}


def test_a_valid_config_resolves_paths_from_its_folder(files):
    (files / "scenes.yaml").write_text("http: {port: 9000}\nscenes:\n"
                                       "  - {name: street, checkpoint: s.ckpt, replay: s.h5, replicas: 2}\n"
                                       "  - {name: demo, demo: true}\n")
    config = load_config(files / "scenes.yaml")
    assert config.http.port == 9000 and [s.name for s in config.scenes] == ["street", "demo"]
    street = config.scene("street")
    assert street.checkpoint == (files / "s.ckpt").resolve() and street.replicas == 2
    assert street.settings_dict()["replay"] == str((files / "s.h5").resolve())
    assert "checkpoint" not in config.scene("demo").settings_dict()


def test_a_live_scene_takes_many_replicas_and_keeps_its_replay_for_its_ingest(files):
    config = parse_config({"scenes": [scene(live=True, replicas=2, max_replicas=3)]}, base=files)
    settings = config.scene("street").settings_dict()
    assert settings["live"] is True and "replay" not in settings, "the replicas read the shared source"
    assert config.scene("street").replay == (files / "s.h5").resolve()


def test_a_scene_with_no_checkpoint_is_a_cold_start_on_its_shared_stream(files):
    config = parse_config({"scenes": [{"name": "street", "replay": "s.h5", "live": True, "replicas": 2}]},
                          base=files)
    street = config.scene("street")
    assert street.cold and street.settings_dict()["checkpoint"] is None
    assert not parse_config({"scenes": [scene()]}, base=files).scene("street").cold


@pytest.mark.parametrize(("entry", "says"), [
    ({"name": "x", "replay": "s.h5"}, "its learner and replicas share: live: true"),
    ({"name": "x", "replay": "s.h5", "live": True, "loop": True}, "loop needs a checkpoint"),
    (scene(name="Street!"), "scenes[0] (Street!): name 'Street!'"),
    (scene(replicas=0), "scenes[0] (street).replicas: Input should be greater than or equal to 1"),
    (scene(settings={"port": 1}), "settings: port are the scene's own keys"),
    (scene(replicas=3, max_replicas=2), "max_replicas (2) is below replicas (3)"),
    (scene(colour="red"), "scenes[0] (street).colour: Extra inputs are not permitted"),
    (scene(checkpoint="missing.ckpt"), "scenes (street).checkpoint: no file"),
    ({"name": "x"}, "give a checkpoint (or demo: true)"),
    (scene(live=True, speed=2.0), "speed 2.0: a live scene runs at the camera's pace"),
])
def test_config_errors_name_the_scene_and_field(files, entry, says):
    with pytest.raises(InvalidInputError, match=r"^scenes\.yaml: ") as info:
        parse_config({"scenes": [entry]}, base=files, source="scenes.yaml")
    assert says in str(info.value)


def test_duplicate_names_and_empty_configs_are_refused(files):
    with pytest.raises(InvalidInputError, match="two scenes are named 'street'"):
        parse_config({"scenes": [scene(), scene()]}, base=files)
    with pytest.raises(InvalidInputError, match="scenes: List should have at least 1 item"):
        parse_config({"scenes": []}, base=files)
    with pytest.raises(InvalidInputError, match="expected a mapping"):
        parse_config(["street"], base=files)


def test_unreadable_and_malformed_files_are_named(files):
    with pytest.raises(InvalidInputError, match="cannot read the Ray config"):
        load_config(files / "nope.yaml")
    (files / "bad.yaml").write_text("scenes: [\n")
    with pytest.raises(InvalidInputError, match=r"bad\.yaml: not valid YAML"):
        load_config(files / "bad.yaml")


def _app() -> FastAPI:
    app = FastAPI()

    @app.get("/echo")
    async def echo(q: int, x_who: str | None = None) -> dict:
        return {"q": q}

    @app.websocket("/ws")
    async def ws(socket: WebSocket) -> None:
        await socket.accept()
        while True:
            text = await socket.receive_text()
            if text == "bye":
                await socket.close(code=4000, reason="asked")
                return
            await socket.send_bytes(text.encode()[::-1])

    return app


def test_an_http_request_runs_through_the_app_in_process():
    result = asyncio.run(http_request(_app(), "GET", "/echo", "q=7", [("Host", "x"), ("Connection", "x")]))
    assert result.status == 200 and result.body == b'{"q":7}'
    assert ("content-type", "application/json") in result.headers
    bad = asyncio.run(http_request(_app(), "GET", "/echo", "q=seven", []))
    assert bad.status == 422


def test_a_websocket_session_runs_through_the_app_in_process():
    async def talk():
        session = WebSocketSession(_app(), "/ws", "", []).start()
        session.send("abc")
        session.send("bye")
        out = [m async for m in session.messages()]
        await session.close()
        return session, out

    session, out = asyncio.run(talk())
    assert session.accepted and out[0].bytes == b"cba"
    assert out[-1].close == 4000 and out[-1].reason == "asked"


def test_only_a_replicas_death_is_retried():
    from ray.exceptions import ActorDiedError

    from edmcgs.server.ray_serve.retry import Retrier, retryable

    wrapped = RuntimeError("task failed")
    wrapped.__cause__ = ActorDiedError()
    assert retryable(ActorDiedError()) and retryable(wrapped)
    assert not retryable(ValueError("a scene's own error"))

    calls = []

    async def flaky():
        calls.append(1)
        if len(calls) < 3:
            raise ActorDiedError()
        return "ok"

    retrier = Retrier(retry_for_s=5)
    assert asyncio.run(retrier.run(flaky)) == "ok" and retrier.retries == 2

    async def broken():
        raise ValueError("no")

    with pytest.raises(ValueError):
        asyncio.run(retrier.run(broken))


def test_the_default_server_never_imports_ray():
    code = ("import sys; import edmcgs.server.cli, edmcgs.server.app, edmcgs.train_cli; "
            "edmcgs.server.app.create_app(); assert 'ray' not in sys.modules, 'ray imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_serve_with_ray_refuses_the_one_scene_flags(capsys):
    from edmcgs.server.cli import main

    assert main(["--ray", "scenes.yaml", "--replay", "x.h5"]) == 2
    assert "--replay cannot be combined with --ray" in capsys.readouterr().err
    assert main(["--ray", "no-such.yaml"]) == 1
    assert "cannot read the Ray config" in capsys.readouterr().err


def test_the_kuberay_manifest_names_a_valid_config_and_the_app_builder():
    import importlib

    import yaml

    from edmcgs.server.ray_serve.config import RayConfig

    root = Path(__file__).resolve().parents[2]
    docs = list(yaml.safe_load_all((root / "docker/kuberay/rayservice.yaml").read_text()))
    config_map = next(d for d in docs if d["kind"] == "ConfigMap")
    config = RayConfig.model_validate(yaml.safe_load(config_map["data"]["scenes.yaml"]))
    assert [s.name for s in config.scenes] == ["street", "lab"]
    service = next(d for d in docs if d["kind"] == "RayService")
    app = yaml.safe_load(service["spec"]["serveConfigV2"])["applications"][0]
    module, name = app["import_path"].split(":")
    assert callable(getattr(importlib.import_module(module), name))
    assert app["args"]["config"].startswith("/etc/edmcgs/")
    assert service["spec"]["rayClusterConfig"]["rayVersion"] == "2.60.0"


def test_the_application_scales_a_scene_between_its_bounds(files):
    from edmcgs.server.ray_serve.app import build

    config = parse_config({"scenes": [scene(name="fixed", replicas=2),
                                      scene(name="elastic", max_replicas=3, settings={"render_workers": 3})]},
                          base=files)
    app = build(config)
    scenes = app._bound_deployment.init_args[0]
    fixed = scenes["fixed"]._bound_deployment._deployment_config
    elastic = scenes["elastic"]._bound_deployment._deployment_config
    assert fixed.num_replicas == 2 and fixed.autoscaling_config is None
    scaling = elastic.autoscaling_config
    assert (scaling.min_replicas, scaling.max_replicas, scaling.target_ongoing_requests) == (1, 3, 3)


@pytest.mark.parametrize("allowlist", [None, ["*"], ["127.0.0.1", "localhost", "::1"], ["cams.example.org"],
                                       ["cams.example.org", "localhost"]])
def test_the_gateways_probe_carries_a_host_the_scene_answers_to(allowlist):
    from edmcgs.server.middleware import AccessMiddleware
    from edmcgs.server.ray_serve.scene import probe_host

    app = AccessMiddleware(_app(), None, allowed_hosts=allowlist)
    probe = asyncio.run(http_request(app, "GET", "/echo", "q=1", [("host", probe_host(allowlist))]))
    assert probe.status == 200
    if allowlist is not None and "*" not in allowlist and "localhost" not in allowlist:
        # what the probe sent before: refused by a scene that narrows its names
        refused = asyncio.run(http_request(app, "GET", "/echo", "q=1", [("host", "localhost")]))
        assert refused.status == 421
