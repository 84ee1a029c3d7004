"""Many scenes on a local Ray Serve (``ray.init(num_cpus=2)``), one Ray for the module: two scenes and
their routing, the websocket through the gateway, a replica killed mid-load with no 5xx, and a scene
whose source fails isolated from the others."""

from __future__ import annotations

import contextlib
import os
import re
import threading
import time

import httpx
import pytest

pytest.importorskip("ray.serve", reason="the 'ray' extra is not installed")

from edmcgs import protocol
from harness.ray_serve import LocalServe, scene_entry
from harness.server import HEIGHT, WIDTH, build_scene

pytestmark = pytest.mark.slow

REPLICA = "x-edmcgs-replica"
TOKEN = "scene-own-token"
SIDE_POSE = [0.05, 0.0, 0.0, 0.995, 0.0, 0.0998, 0.0]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ray-scenes")
    common = dict(width=WIDTH, height=HEIGHT, event_rate=20_000, init_points=1000, control_points=32)
    rec_a, ckpt_a = build_scene(folder / "a", seed=1, **common)
    rec_b, ckpt_b = build_scene(folder / "b", seed=2, t0_us=1_700_000_000_000_000, **common)
    broken = folder / "broken.h5"
    broken.write_bytes(b"this is not an HDF5 recording")
    scenes = [scene_entry("alpha", ckpt_a, rec_a),
              scene_entry("beta", ckpt_b, rec_b, replicas=2),
              scene_entry("broken", ckpt_a, broken),
              scene_entry("secret", ckpt_a, rec_a, token=TOKEN),
              # About its shared source: no online fits, which would keep both its replicas busy
              # for the whole module on 2 cores (they are tested in the single-process e2e).
              {**scene_entry("cam", ckpt_a, rec_a, replicas=2, online_fit_steps=0, online_transition="none"),
               "live": True}]
    with LocalServe(scenes) as local:
        local.wait_renderable("alpha")
        local.wait_renderable("beta")
        local.wait_renderable("secret", token=TOKEN)
        yield local


def test_scenes_lists_every_scene_with_its_health(cluster):
    body = httpx.get(cluster.url + "/scenes", timeout=30).json()
    by_name = {s["name"]: s for s in body["scenes"]}
    assert list(by_name) == ["alpha", "beta", "broken", "secret", "cam"]
    assert by_name["beta"]["replicas"] == 2 and by_name["beta"]["url"] == "/scenes/beta/"
    assert by_name["alpha"]["health"]["ready"] is True and by_name["beta"]["health"]["ready"] is True
    assert by_name["broken"]["health"]["ready"] is False
    assert by_name["secret"]["health"]["ready"] is True, "the gateway asks with the scene's own token"


def test_each_scene_answers_under_its_name(cluster):
    a = httpx.get(cluster.url + "/scenes/alpha/scene", timeout=30).json()
    b = httpx.get(cluster.url + "/scenes/beta/scene", timeout=30).json()
    assert a["t_start_us"] < 1_700_000_000_000_000 <= b["t_start_us"], "each name reaches its own scene"
    r = httpx.get(cluster.url + "/scenes/beta/render", params={"t": 0.5, "format": "png"}, timeout=30)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert r.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert int(r.headers["x-edmcgs-t-us"]) == b["t_start_us"] + 500_000


def test_a_scenes_errors_are_the_single_process_ones(cluster):
    r = httpx.get(cluster.url + "/scenes/alpha/render", params={"t": 0.5, "width": 0}, timeout=30)
    assert r.status_code == 422 and r.json()["param"] == "width"
    r = httpx.get(cluster.url + "/scenes/alpha/render", params={"t": 99.0}, timeout=30)
    assert r.status_code == 416 and r.json()["valid_range"] is not None
    r = httpx.get(cluster.url + "/scenes/nowhere/render", timeout=30)
    assert r.status_code == 404 and "alpha" in r.json()["detail"]


def test_the_viewer_is_served_per_scene(cluster):
    r = httpx.get(cluster.url + "/scenes/alpha", timeout=30, follow_redirects=True)
    assert r.status_code == 200 and "<html" in r.text.lower()
    assert str(r.url).endswith("/scenes/alpha/")
    assert httpx.get(cluster.url + "/scenes/alpha/viewer.js", timeout=30).status_code == 200
    assert 'href="scenes/beta/"' in httpx.get(cluster.url + "/", timeout=30).text


def test_the_viewer_picks_a_scene_from_the_gateways_list(cluster):
    from tests.support.viewer import chromium

    with chromium() as browser:
        page = browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(cluster.url + "/scenes/alpha/")
        page.wait_for_function("!document.getElementById('scene-picker').hidden", timeout=30_000)
        options = page.eval_on_selector_all("#scene-picker option", "os => os.map(o => o.value)")
        assert options == ["alpha", "beta", "broken", "secret", "cam"]
        assert page.eval_on_selector("#scene-picker", "p => p.value") == "alpha"
        page.wait_for_function("window.edmcgsViewer.state.scene !== null", timeout=30_000)
        alpha_start = page.evaluate("window.edmcgsViewer.state.scene.t_start_us")
        page.select_option("#scene-picker", "beta")
        page.wait_for_url("**/scenes/beta/", timeout=30_000)
        page.wait_for_function("window.edmcgsViewer && window.edmcgsViewer.state.scene", timeout=30_000)
        beta_start = page.evaluate("window.edmcgsViewer.state.scene.t_start_us")
        # the new page fills its picker from /scenes on its own schedule
        page.wait_for_function("document.getElementById('scene-picker').value === 'beta'", timeout=30_000)
        page.close()
    assert alpha_start < 1_700_000_000_000_000 <= beta_start, "the picker switched scenes"
    assert errors == []


def test_a_scenes_docs_show_its_own_schema_under_its_prefix(cluster):
    page = httpx.get(cluster.url + "/scenes/beta/docs", timeout=30)
    assert page.status_code == 200 and "/scenes/beta/openapi.json" in page.text
    assert "/scenes/beta/docs/assets/swagger-ui-bundle.js" in page.text
    assert httpx.get(cluster.url + "/scenes/beta/docs/assets/swagger-ui-bundle.js",
                     timeout=30).status_code == 200
    schema = httpx.get(cluster.url + "/scenes/beta/openapi.json", timeout=30).json()
    assert "/scenes/beta/render" in schema["paths"] and "/render" not in schema["paths"]
    assert "/scenes" not in schema["paths"], "the scene's schema, not the gateway's"
    assert schema["info"]["title"].endswith("scene beta")


def test_the_websocket_streams_through_the_gateway(cluster):
    from websockets.sync.client import connect

    url = cluster.url.replace("http://", "ws://") + "/scenes/beta/stream"
    with connect(url, open_timeout=30) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.0, "t1": 0.5, "fps": 20, "speed": 1.0,
                               "format": "raw"}))
        kinds, frames = [], []
        deadline = time.monotonic() + 60
        while len(frames) < 3 and time.monotonic() < deadline:
            message = protocol.unpack(ws.recv(timeout=30))
            kinds.append(message["type"])
            if message["type"] == "frame":
                frames.append(message)
        assert kinds[0] == "subscribed" and len(frames) == 3
        # A second message: answered once, and the stream goes on with the new size.
        ws.send(protocol.pack({"width": 32}))
        while True:
            message = protocol.unpack(ws.recv(timeout=30))
            if message["type"] == "frame" and message["width"] == 32:
                break
            assert message["type"] in ("frame", "subscribed", "end")
        assert kinds.count("subscribed") == 1


def test_a_sweep_keeps_its_position_when_a_pose_arrives_mid_stream(cluster):
    """One replica-side session for the connection's life: a new pose reaches the running sweep, which
    goes on from where it was (its seq and t keep rising) instead of starting over."""
    from websockets.sync.client import connect

    url = cluster.url.replace("http://", "ws://") + "/scenes/beta/stream"
    with connect(url, open_timeout=30) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.0, "t1": 1.5, "fps": 10, "speed": 1.0,
                               "format": "raw"}))
        assert protocol.unpack(ws.recv(timeout=30))["type"] == "subscribed"
        before = [protocol.unpack(ws.recv(timeout=30)) for _ in range(4)]
        assert [m["type"] for m in before] == ["frame"] * 4
        ws.send(protocol.pack({"pose": SIDE_POSE}))
        after, replies = [], 0
        while len(after) < 4:
            message = protocol.unpack(ws.recv(timeout=30))
            if message["type"] == "subscribed":
                replies += 1
            else:
                assert message["type"] == "frame", message
                after.append(message)
    assert replies == 1, "the pose update is answered once"
    ts = [m["t"] for m in before + after]
    seqs = [m["seq"] for m in before + after]
    assert ts == sorted(ts) and ts[-1] > ts[3] >= 0.25, f"the sweep started over: t = {ts}"
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), f"seq started over: {seqs}"


def test_a_scene_with_its_own_token_refuses_without_it_and_leaves_the_others_open(cluster):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    url = cluster.url + "/scenes/secret/render"
    r = httpx.get(url, params={"t": 0.5}, timeout=30)
    assert r.status_code == 401 and r.json()["error"] == "unauthorized"
    assert httpx.get(url, params={"t": 0.5}, headers={"Authorization": "Bearer wrong"},
                     timeout=30).status_code == 401
    r = httpx.get(url, params={"t": 0.5}, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30)
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/")
    assert httpx.get(cluster.url + "/scenes/alpha/render", params={"t": 0.5}, timeout=30).status_code == 200

    ws_url = cluster.url.replace("http://", "ws://") + "/scenes/secret/stream"
    sweep = protocol.pack({"mode": "sweep", "t0": 0.0, "t1": 0.5, "fps": 10, "format": "raw"})
    with connect(ws_url, open_timeout=30) as ws:
        ws.send(sweep)
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=30)
    assert closed.value.rcvd.code == 1008
    with connect(ws_url + f"?token={TOKEN}", open_timeout=30) as ws:
        ws.send(sweep)
        assert protocol.unpack(ws.recv(timeout=30))["type"] == "subscribed"
        assert protocol.unpack(ws.recv(timeout=30))["type"] == "frame"


def test_a_scenes_metrics_gather_every_replica_and_the_gateways_counters(cluster):
    for _ in range(6):  # requests on both replicas (power of two choices spreads them)
        httpx.get(cluster.url + "/scenes/beta/render", params={"t": 0.5}, timeout=30)
    deadline = time.monotonic() + 30
    while True:
        r = httpx.get(cluster.url + "/scenes/beta/metrics", timeout=30)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        replicas = set(re.findall(r'^edmcgs_http_requests_total\{replica="([^"]+)"', r.text, re.M))
        if len(replicas) == 2:
            break
        assert time.monotonic() < deadline, f"replicas reporting: {replicas}\n{r.text[:2000]}"
        time.sleep(0.5)
    assert r.text.count("# TYPE edmcgs_http_requests_total counter") == 1, "one family, both replicas"
    assert 'edmcgs_gateway_replicas_reporting{scene="beta"} 2' in r.text
    assert re.search(r'^edmcgs_gateway_retries_total\{scene="beta"\} \d+$', r.text, re.M)
    # The secret scene's metrics follow its token.
    assert httpx.get(cluster.url + "/scenes/secret/metrics", timeout=30).status_code == 401
    r = httpx.get(cluster.url + "/scenes/secret/metrics", headers={"Authorization": f"Bearer {TOKEN}"},
                  timeout=30)
    assert r.status_code == 200 and 'edmcgs_gateway_replicas_reporting{scene="secret"}' in r.text


def test_a_live_scenes_replicas_share_its_one_source(cluster):
    """A recording played as a live camera: one ingest replica reads it, both render replicas pull
    its batches into their own rings, and neither misses any."""
    scene = next(s for s in httpx.get(cluster.url + "/scenes", timeout=30).json()["scenes"]
                 if s["name"] == "cam")
    assert scene["source"] == {"kind": "live", "shared": True, "replay": "scene.h5"}
    assert cluster.running_replicas("ingest-cam") == 1 and cluster.running_replicas("scene-cam") == 2
    replicas: set[str] = set()
    deadline = time.monotonic() + 60
    while len(replicas) < 2:
        assert time.monotonic() < deadline, f"only {replicas} rendered the live head"
        r = httpx.get(cluster.url + "/scenes/cam/render", params={"format": "jpeg"}, timeout=30)
        if r.status_code == 200:
            replicas.add(r.headers[REPLICA])
    deadline = time.monotonic() + 30
    while True:
        text = httpx.get(cluster.url + "/scenes/cam/metrics", timeout=30).text
        ingested = {m[0]: float(m[1]) for m in re.findall(
            r'^edmcgs_events_ingested_total\{replica="([^"]+)"\} (\S+)$', text, re.M)}
        if len(ingested) == 2:
            break
        assert time.monotonic() < deadline, text[:2000]
        time.sleep(0.5)
    assert all(n > 0 for n in ingested.values()), ingested
    behind = re.findall(r'^edmcgs_events_dropped_total\{replica="[^"]+",reason="behind"\} (\S+)$', text, re.M)
    assert behind and all(float(v) == 0 for v in behind), "no replica fell behind the shared ring"


def test_a_live_scene_reconnects_when_its_ingest_replica_dies(cluster):
    """Serve replaces the killed ingest replica; each render replica's source reconnects to the new one
    (the same path as a camera unplugged and back), renders never fail, and each replica's head moves
    on past where it stood: the new replica's events come after the old one's on the wall clock."""
    def head() -> tuple[str, int]:
        r = httpx.get(cluster.url + "/scenes/cam/render", params={"format": "jpeg"}, timeout=60)
        assert r.status_code == 200, r.text[:500]
        return r.headers[REPLICA], int(r.headers["x-edmcgs-t-us"])

    def heads(deadline: float, past: dict[str, int] | None = None) -> dict[str, int]:
        """Each render replica's live head (past ``past``'s, when given), by polling until both answer."""
        seen: dict[str, int] = {}
        while len(seen) < 2:
            assert time.monotonic() < deadline, f"heads {seen}, waiting to pass {past}"
            replica, t_us = head()
            if past is None or t_us > past[replica]:
                seen[replica] = t_us
        return seen

    victims = cluster.replica_actors("ingest-cam")
    assert len(victims) == 1, victims
    before = heads(time.monotonic() + 60)
    cluster.kill_replica(victims[0])
    deadline = time.monotonic() + 150
    while cluster.running_replicas("ingest-cam") < 1 or cluster.replica_actors("ingest-cam") == victims:
        assert time.monotonic() < deadline, "the ingest replica was not replaced"
        head()  # the render replicas keep answering from what their rings hold
        time.sleep(0.5)
    reconnected: dict[str, float] = {}
    while len(reconnected) < 2 or not all(v >= 1 for v in reconnected.values()):
        assert time.monotonic() < deadline, f"the render replicas did not reconnect: {reconnected}"
        text = httpx.get(cluster.url + "/scenes/cam/metrics", timeout=30).text
        reconnected = {m[0]: float(m[1]) for m in re.findall(
            r'^edmcgs_source_reconnects_total\{replica="([^"]+)"\} (\S+)$', text, re.M)}
        time.sleep(0.5)
    health = httpx.get(cluster.url + "/scenes/cam/healthz", timeout=30).json()
    assert health["ready"] is True and health["source"] != "error", health
    heads(time.monotonic() + 60, past=before)  # the new ingest's events arrive on both replicas


def test_a_replica_killed_mid_load_costs_no_failed_request(cluster):
    url = cluster.url + "/scenes/beta/render"
    statuses: list[int] = []
    replicas: set[str] = set()
    stop = threading.Event()

    def load():
        with httpx.Client(timeout=60) as client:
            while not stop.is_set():
                r = client.get(url, params={"t": 0.25, "format": "jpeg"})
                statuses.append(r.status_code)
                if r.status_code == 200:
                    replicas.add(r.headers[REPLICA])

    threads = [threading.Thread(target=load) for _ in range(3)]
    for t in threads:
        t.start()
    try:
        deadline = time.monotonic() + 60
        while len(replicas) < 2:  # both replicas answer before one is killed
            assert time.monotonic() < deadline, f"only {replicas} answered"
            time.sleep(0.1)
        victim = sorted(replicas)[0]
        before = len(statuses)
        cluster.kill_replica(victim)
        # Replaced: two replicas running again, and the replacement (a new name) answers. It starts
        # (torch, the checkpoint, its replay's span) under three clients and the other scenes, on 2 cores.
        deadline = time.monotonic() + 180
        while cluster.running_replicas("scene-beta") < 2 or len(replicas) < 3:
            assert time.monotonic() < deadline, "the killed replica was not replaced"
            time.sleep(0.2)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=90)
    failed = [s for s in statuses if s != 200]
    assert failed == [], f"{len(failed)} of {len(statuses)} requests failed: {sorted(set(failed))}"
    assert len(statuses) > before


def test_a_failing_source_is_reported_by_its_scene_alone(cluster):
    r = httpx.get(cluster.url + "/scenes/broken/healthz", timeout=30)
    assert r.status_code == 503
    body = r.json()
    assert body["ready"] is False and body["source"] == "error" and "broken.h5" in body["source_error"]
    r = httpx.get(cluster.url + "/scenes/broken/render", params={"t": 0.5}, timeout=30)
    assert r.status_code == 503 and r.json()["error"] == "not_ready"
    for name in ("alpha", "beta"):
        assert httpx.get(f"{cluster.url}/scenes/{name}/healthz", timeout=30).status_code == 200
        r = httpx.get(f"{cluster.url}/scenes/{name}/render", params={"t": 0.5}, timeout=30)
        assert r.status_code == 200
    health = httpx.get(cluster.url + "/healthz", timeout=30).json()
    assert health["scenes"] == {"alpha": True, "beta": True, "broken": False, "secret": True, "cam": True}


def test_a_stream_and_a_render_outlive_a_scenes_only_replica(cluster):
    """Last in the module: alpha's one replica is killed under an open stream and a render; the
    stream goes on from a replacement (its seq starts over) and the render waits for it: no error."""
    from websockets.sync.client import connect

    victim = httpx.get(cluster.url + "/scenes/alpha/scene", timeout=30).headers[REPLICA]
    url = cluster.url.replace("http://", "ws://") + "/scenes/alpha/stream"
    with connect(url, open_timeout=30) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.0, "t1": 1.5, "fps": 10, "speed": 1.0, "loop": True,
                               "format": "raw"}))
        assert protocol.unpack(ws.recv(timeout=30))["type"] == "subscribed"
        assert protocol.unpack(ws.recv(timeout=30))["type"] == "frame"
        cluster.kill_replica(victim)
        r = httpx.get(cluster.url + "/scenes/alpha/render", params={"t": 0.5}, timeout=120)
        assert r.status_code == 200 and r.headers[REPLICA] != victim
        kinds = []
        deadline = time.monotonic() + 90
        while kinds.count("frame") < 5 and time.monotonic() < deadline:
            kinds.append(protocol.unpack(ws.recv(timeout=60))["type"])
        assert kinds.count("frame") >= 5 and "error" not in kinds and "subscribed" not in kinds


def test_a_replaced_gateway_streams_and_gathers_metrics_again(cluster):
    """After the last: the gateway's replica is killed; Serve's replacement makes its mailbox and metrics
    board again, so a new websocket streams and a scene's metrics list every replica once more."""
    from websockets.sync.client import connect

    victims = cluster.replica_actors("gateway")
    assert len(victims) == 1, victims
    cluster.kill_replica(victims[0])
    deadline = time.monotonic() + 120
    while True:
        assert time.monotonic() < deadline, "the gateway was not replaced"
        try:
            if httpx.get(cluster.url + "/scenes", timeout=10).status_code == 200 and \
                    cluster.replica_actors("gateway") not in ([], victims):
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    url = cluster.url.replace("http://", "ws://") + "/scenes/beta/stream"
    with connect(url, open_timeout=30) as ws:
        ws.send(protocol.pack({"mode": "sweep", "t0": 0.0, "t1": 0.5, "fps": 20, "speed": 1.0,
                               "format": "raw"}))
        kinds = [protocol.unpack(ws.recv(timeout=60))["type"] for _ in range(3)]
        assert kinds == ["subscribed", "frame", "frame"], kinds
    while True:
        r = httpx.get(cluster.url + "/scenes/beta/metrics", timeout=30)
        if 'edmcgs_gateway_replicas_reporting{scene="beta"} 2' in r.text:
            break
        assert time.monotonic() < deadline, r.text[-2000:]
        time.sleep(0.5)


def test_the_gateways_own_pages_refuse_a_foreign_host(cluster):
    for path in ("/scenes", "/", "/healthz", "/docs", "/openapi.json", "/scenes/nowhere/render"):
        r = httpx.get(cluster.url + path, headers={"Host": "evil.com"}, timeout=30)
        assert r.status_code == 421, (path, r.status_code)
        r = httpx.get(cluster.url + path, headers={"Host": "127.0.0.1:1@evil.com"}, timeout=30)
        assert r.status_code == 421, (path, r.status_code)
    assert httpx.get(cluster.url + "/scenes/alpha/scene", headers={"Host": "evil.com"},
                     timeout=30).status_code == 421, "a scene's own route: its replica's check"


def _ray_memory_mb() -> dict[int, tuple[str, float, float]]:
    """(name, resident MB, of which Ray's shared object store pages) of the Ray processes this test
    process started (GCS, raylet, the proxy, the gateway, its mailbox, the replicas): its descendants."""
    from pathlib import Path

    parent = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parent[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    mine, grew = {os.getpid()}, True
    while grew:
        grew = False
        for pid, ppid in parent.items():
            if ppid in mine and pid not in mine:
                mine.add(pid)
                grew = True
    out = {}
    for pid in mine - {os.getpid()}:
        try:
            name = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
            rss, shared = (int(status[k].split()[0]) / 1024 for k in ("VmRSS", "RssShmem"))
        except (OSError, KeyError, ValueError):
            continue
        out[pid] = (name.split()[0][:40], rss, shared)
    return out


def test_big_messages_are_refused_and_leave_no_memory_behind(cluster):
    """A 16 MiB message (Serve's proxy takes it) is closed with 1009 by the gateway; then 1,000 messages
    of 1 MiB (each answered with the scene's error by the gateway) leave every Ray process's own memory
    within 100 MB of where it was. Its resident size also counts the pages of Ray's shared object store it
    has mapped (the proxy hands the gateway each message through it), one store for all processes."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    url = cluster.url.replace("http://", "ws://") + "/scenes/alpha/stream"
    with connect(url, open_timeout=30, max_size=None) as ws:
        ws.send(bytes(16 << 20))
        with pytest.raises(ConnectionClosed) as info:
            ws.recv(timeout=60)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1009
    before, sent, big = _ray_memory_mb(), 0, bytes(1 << 20)
    while sent < 1000:
        with connect(url, open_timeout=30, max_size=None) as ws:
            with contextlib.suppress(ConnectionClosed):  # closed for sending too fast: again
                while sent < 1000:
                    ws.send(big)
                    sent += 1
                    assert protocol.unpack(ws.recv(timeout=60))["type"] == "error"
    after = _ray_memory_mb()
    grown = {after[pid][0]: (round(after[pid][1] - rss), round(after[pid][2] - shared))
             for pid, (_, rss, shared) in before.items() if pid in after}
    print(f"resident MB grown after {sent} messages of 1 MiB (of which shared object store): {grown}")
    own = {name: rss - shared for name, (rss, shared) in grown.items()}
    assert own and max(own.values()) < 100, grown
