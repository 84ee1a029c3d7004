"""A cold start in process (server/live/learning.py, learner.py, timebase.FramesTimebase): before any model
the event camera's view is the newest frame moved by the events since, and nothing else renders; the
learner's rounds publish models over the anchors received so far, warm-started from the round before;
the engine swaps a newer model in whole, and a render already running finishes on the one it began."""

from __future__ import annotations

import queue
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from edmcgs.geometry import Intrinsics
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.model.online.bounds import integrate
from edmcgs.model.train.warm import warm_start
from edmcgs.pipeline import build_config, new_model, training_data
from edmcgs.sensor.buffer.anchors import AnchorStore
from edmcgs.sensor.buffer.ring import EventRingBuffer
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import read_recording
from edmcgs.server.engine import Engine
from edmcgs.server.errors import NotReady
from edmcgs.server.live.clock import Timeline
from edmcgs.server.live.config import LearnConfig
from edmcgs.server.live.learner import Learner, Stream
from edmcgs.server.live.timebase import FramesTimebase, StreamMeta, Timebase
from harness.server import build_scene

W, H = 64, 48
TINY = ("init_points=300", "num_control_points=16", "deform_width=16", "deform_depth=2")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 1 s recording at 64x48, a frame every 50 ms (anchors every 100 ms: every other one held out)."""
    rec_path, ckpt = build_scene(tmp_path_factory.mktemp("cold"), width=W, height=H, duration_s=1.0,
                                 anchor_every_s=0.1, frames_per_anchor=2, event_rate=20_000, init_points=300,
                                 control_points=16, event_branch_seed=0)
    return read_recording(rec_path), ckpt


def _frames_engine(rec, until_us: int) -> tuple[Engine, AnchorStore]:
    """An engine before any model, fed as the ingest thread feeds it up to ``until_us``."""
    t0 = int(rec.anchors.t_us[0])
    ring, frames = EventRingBuffer(10**6), AnchorStore(64)
    ring.push(rec.events.time_slice(t0, until_us), complete_until_us=until_us)
    frames.add_frames(rec.anchors.time_slice(t0, until_us))
    meta = StreamMeta(t0, Intrinsics(60.0, 60.0, 31.5, 23.5, W, H), W, H, 3, 0.2)
    engine = Engine(FramesTimebase(meta, frames), ring, cache_size=4)
    engine.timeline = Timeline(t0, t0)
    return engine, frames


def test_before_any_model_the_camera_view_is_the_newest_frame_moved_by_the_events_since(scene):
    rec, _ = scene
    t0 = int(rec.anchors.t_us[0])
    head = t0 + 320_000
    engine, frames = _frames_engine(rec, head + 1)
    out = engine.render(None, None, W, H)
    tau = frames.tau(head)
    assert out.instant.t_us == head and out.instant.anchor_us == tau == t0 + 300_000
    assert out.anchor == "frame" and out.model_version is None and out.projected
    emap = accumulate(rec.events.time_slice(tau, head), W, H)
    assert np.abs(emap).sum() > 0
    want = np.rint(np.clip(integrate(frames.anchor_at(tau).image, emap, 0.2), 0, 1) * 255)
    assert np.abs(out.pixels.astype(int) - want.astype(int)).max() <= 1
    assert engine.render(None, None, 32, 24).pixels.shape == (24, 32, 3)  # any size
    assert engine.renderable() == [(t0, head)]
    assert [s.value for s, *_ in engine.timebase.tau_ranges(head)] == ["stream"]
    # nothing else renders without a model: a pose, another mode, the Gaussians
    with pytest.raises(NotReady, match="no model has been learnt yet"):
        engine.render(None, np.eye(4), W, H)
    with pytest.raises(NotReady):
        engine.render(None, None, W, H, mode="depth")
    with pytest.raises(NotReady):
        engine.state(out.instant)


def test_a_swap_serves_the_new_model_and_a_running_render_finishes_on_its_own(scene):
    rec, ckpt = scene
    engine, _ = _frames_engine(rec, int(rec.anchors.t_us[0]) + 400_001)
    before = engine.timebase
    model = load_checkpoint(ckpt)
    engine.swap(Timebase(model, version=3))
    t = int(model.meta.anchors_us[2]) + 30_000
    out = engine.render(t, None, W, H)
    assert out.anchor == "checkpoint" and out.model_version == 3 and not out.projected
    # with the stream's frames kept (a cold start's), its view within the span is projected onto the
    # frame at its anchor too, as past the span; any other pose is the model's alone
    engine.swap(Timebase(model, None, before.frames, version=4))
    kept = engine.render(t, None, W, H)
    assert kept.projected and kept.model_version == 4
    assert kept.instant.anchor_us == int(model.meta.anchors_us[2])
    assert not engine.render(t, model.meta.trajectory.at(t) @ _shifted(0.01), W, H).projected
    # a render that took the old timebase before the swap resolves and renders with it alone
    old = engine.resolve(None, before)
    assert before.start(old).kind == "frame"
    # the cache tells the two apart: the same instant under each timebase is its own entry
    assert before.serial != engine.timebase.serial


def test_warm_start_copies_the_shared_networks_and_only_a_layer_of_the_same_placement(scene):
    rec, _ = scene
    data = training_data(rec)
    cfg = build_config("real", list(TINY), rec)
    a, b = new_model(data, cfg), new_model(data, cfg.replace(seed=1))
    with torch.no_grad():
        for p in a.parameters():
            p.add_(0.01)
        a.event_scale.fill_(0.5)
    copied = warm_start(b, a)
    assert copied == ["prior", "encoder", "transition", "background layer"]
    for name in ("prior", "encoder", "transition", "bg_layer"):
        for x, y in zip(getattr(a, name).state_dict().values(), getattr(b, name).state_dict().values(),
                        strict=True):
            assert torch.equal(x, y), name
    assert float(b.event_scale) == 0.5
    assert not torch.equal(a.gaussians.means, b.gaussians.means)  # lifted from its own anchors
    wider = new_model(data, cfg.replace(deform_width=32))
    assert "prior" not in warm_start(wider, a)  # shapes differ: left as initialised


def _shifted(dx: float) -> np.ndarray:
    m = np.eye(4)
    m[0, 3] = dx
    return m


class _Outbox(list):
    def put(self, item):
        self.append(item)


def _feed(stream: Stream, rec, lo_us: int, hi_us: int) -> None:
    ev, frames = rec.events.time_slice(lo_us, hi_us), rec.anchors.time_slice(lo_us, hi_us)
    stream.add(ev.t, ev.x, ev.y, ev.p, frames.t_us, frames.images)


def test_the_learner_publishes_rounds_over_the_anchors_received_and_saves_what_resumes(scene, tmp_path):
    rec, _ = scene
    t0 = int(rec.anchors.t_us[0])
    config = LearnConfig(workdir=tmp_path, intrinsics=(60.0, 60.0, 31.5, 23.5), preset="demo",
                         overrides=(*TINY, "iterations=60"), anchor_fps=10.0, min_anchors=3, first_steps=10,
                         publish_s=1e9, eval_frames=2)
    stream, outbox = Stream(W, H), _Outbox()
    learner = Learner(config, stream, outbox)
    assert not learner.step()  # nothing yet
    _feed(stream, rec, t0, t0 + 250_000)  # anchors at 0, 0.1, 0.2 s; frames between held out
    while not outbox:
        assert learner.step()
    first = outbox[-1]
    assert first["kind"] == "published" and first["version"] == 1 and first["steps"] == 10
    assert first["anchors"] == 3 and first["span_us"][0] == t0
    assert first["heldout"]["frames"] == 2 and np.isfinite(first["heldout"]["psnr"])
    assert load_checkpoint(first["path"]).meta.anchors_us.tolist() == [t0, t0 + 100_000, t0 + 200_000]
    _feed(stream, rec, t0 + 250_000, t0 + 750_000)
    while len(outbox) < 2:
        learner.step()
    second = outbox[-1]
    assert second["version"] == 2 and second["anchors"] == 8 and second["steps"] == 20  # twice the first
    # No new anchor: the same model goes on, on the preset's whole schedule, from where it was
    model, step = learner.round.trainer.model, learner.round.trainer.step
    learner.step()
    assert learner.round.lengthened and learner.round.steps == 60 and model.config.iterations == 60
    assert learner.round.trainer.model is model and learner.round.trainer.step == step + 5
    # ... until new anchors arrive: a new round over them at once, long before that schedule's end
    _feed(stream, rec, t0 + 750_000, rec.t_range_us[1] + 1)
    learner.step()
    assert learner.round.anchors == 11 and learner.round.trainer.model is not model
    while len(outbox) < 3:
        learner.step()
    third = outbox[-1]
    assert third["version"] == 3 and third["anchors"] == 11 and third["steps"] == 60
    saved = learner.save()
    assert Path(saved["checkpoint"]).name == "learned.ckpt" and saved["steps"] == learner.round.trainer.step
    assert (tmp_path / "learned.ckpt.train-state").is_file()
    back = read_recording(saved["recording"])  # what the model learnt from: a pair train --resume takes
    assert len(back.anchors) == 11 and len(back.held_out) == 10 and len(back.events) == len(rec.events)
    assert back.anchors.t_us.tolist() == load_checkpoint(saved["checkpoint"]).meta.anchors_us.tolist()
    kept = sorted(p.name for p in tmp_path.glob("learned-*.ckpt"))
    assert kept == ["learned-0002.ckpt", "learned-0003.ckpt"]


def _publishing_every_chunk(rec, workdir, first_steps: int) -> tuple[Learner, Stream, _Outbox]:
    """A learner due to publish at every chunk of steps (publish_s 0), fed the first 250 ms of ``rec``."""
    config = LearnConfig(workdir=workdir, intrinsics=(60.0, 60.0, 31.5, 23.5), preset="demo",
                         overrides=TINY, anchor_fps=10.0, min_anchors=3, first_steps=first_steps,
                         publish_s=0.0, eval_frames=1, poses="static")
    stream, outbox = Stream(W, H), _Outbox()
    t0 = int(rec.anchors.t_us[0])
    _feed(stream, rec, t0, t0 + 250_000)
    return Learner(config, stream, outbox), stream, outbox


def test_a_new_round_goes_live_once_it_has_trained_each_anchor_as_long_as_the_model_live(scene, tmp_path):
    rec, _ = scene
    t0 = int(rec.anchors.t_us[0])
    learner, stream, outbox = _publishing_every_chunk(rec, tmp_path, first_steps=10)
    while len(outbox) < 2:  # due at every chunk: published at 5 and 10 steps
        learner.step()
    assert [m["steps"] for m in outbox] == [5, 10]
    _feed(stream, rec, t0 + 250_000, rec.t_range_us[1] + 1)
    while len(outbox) < 3:
        learner.step()
    # the model live trained its 3 anchors 10 steps: the new round's 11 would need 37, more than its whole
    # schedule (20 steps), so its first model went live at the round's end, not at 5, 10 or 15 steps
    assert outbox[-1]["anchors"] == 11 and outbox[-1]["steps"] == 20
    while len(outbox) < 4:  # the same anchors from then on: every chunk is due
        learner.step()
    assert outbox[-1]["anchors"] == 11 and outbox[-1]["steps"] == 25


def test_a_model_goes_live_only_once_the_gaussians_a_round_added_have_trained(scene, tmp_path):
    """Published a few steps after a densification, a model draws its new Gaussians untrained: the round
    trains SETTLE_STEPS first (or reaches its end)."""
    from edmcgs.server.live.learner import SETTLE_STEPS

    learner, _, outbox = _publishing_every_chunk(scene[0], tmp_path, first_steps=80)
    while not outbox:  # due at every chunk
        learner.step()
    assert outbox[0]["steps"] == 5
    learner.round.trainer.grown_at = 10  # as a densification at step 10 would
    while len(outbox) < 2:
        learner.step()
    assert outbox[1]["steps"] == 10 + SETTLE_STEPS
    learner.round.trainer.grown_at = 75  # 5 steps before the round's end: the end publishes
    while len(outbox) < 3:
        learner.step()
    assert outbox[2]["steps"] == 80


def test_the_learner_process_reports_and_saves_when_told_to_stop(scene, tmp_path):
    """The process itself (spawned as the service spawns it): fed, it publishes; told to stop, it saves."""
    from edmcgs.sensor.sources.base import SensorBatch
    from edmcgs.server.live.learning import Learning

    rec, _ = scene
    config = LearnConfig(workdir=tmp_path, intrinsics=(60.0, 60.0, 31.5, 23.5), preset="demo",
                         overrides=TINY, anchor_fps=10.0, first_steps=5, publish_s=1e9, eval_frames=1)
    taken = queue.Queue()
    learning = Learning(config, W, H)
    learning.on_model = lambda model, report: taken.put((model, report))
    learning.start()
    try:
        t0 = int(rec.anchors.t_us[0])
        for lo in range(t0, int(rec.t_range_us[1]) + 1, 100_000):
            hi = lo + 100_000
            learning.feed(SensorBatch(rec.events.time_slice(lo, hi), rec.anchors.time_slice(lo, hi),
                                      t_end_us=hi))
        model, report = taken.get(timeout=120)
        assert report["version"] == 1 and len(model.meta.anchors_us) == report["anchors"] >= 3
        # on_model runs before the reader thread counts the model served: wait for that, bounded
        deadline = time.monotonic() + 30
        while learning.info()["model"] is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert learning.info()["model"]["version"] == 1 and learning.info()["running"]
    finally:
        saved = learning.close()
    assert saved is not None and Path(saved["checkpoint"]).is_file() and Path(saved["recording"]).is_file()
    assert not learning.process.is_alive() and learning.error is None


def test_a_moving_camera_s_rounds_take_poses_from_their_frames_in_one_world_frame(tmp_path):
    """No poses stated: each round runs structure from motion (the first over its anchor frames, later ones
    over every frame received), trains the moving preset on them, and keeps the world frame of the round
    before (a held pose means the same place)."""
    from harness.pose_scenes import rigid_sweep, trajectory_error

    t_us, images, truth, k = rigid_sweep(26, 12.5)  # 2 s of a camera on an arc, lego frozen in front
    config = LearnConfig(workdir=tmp_path, intrinsics=(k.fx, k.fy, k.cx, k.cy), preset="auto",
                         overrides=(*TINY, "iterations=20"), anchor_fps=6.25, min_anchors=7, first_steps=10,
                         publish_s=1e9, eval_frames=2)
    stream, outbox = Stream(k.width, k.height), _Outbox()
    learner = Learner(config, stream, outbox)
    empty = np.zeros(0, np.int64), np.zeros(0, np.int16), np.zeros(0, np.int16), np.zeros(0, np.int8)
    stream.add(*empty, t_us[:14], images[:14])  # 7 anchors
    while not outbox:
        assert learner.step()
    first = outbox[-1]
    assert first["camera"] == "estimated: moving" and first["preset"] == "moving"
    one = load_checkpoint(first["path"])
    assert len(one.meta.anchors_us) == 7 and one.gaussians.static().any()  # the static set, on SfM's points
    anchors = one.meta.anchors_us
    np.testing.assert_array_equal(one.meta.trajectory.t_us, anchors)  # the first round maps its anchors
    rmse, length = trajectory_error(anchors, one.meta.trajectory.at(anchors), truth[:14:2])
    assert rmse < 0.02 * length
    stream.add(*empty, t_us[14:], images[14:])
    while len(outbox) < 2:
        learner.step()
    second = outbox[-1]
    assert second["anchors"] == 13 and second["camera"] == "estimated: moving"
    two = load_checkpoint(second["path"])
    # later rounds map every frame: the held-out frames have poses of their own, not the anchors' blend
    assert np.isin(t_us[1::2], two.meta.trajectory.t_us).mean() >= 0.9
    rmse, length = trajectory_error(t_us, two.meta.trajectory.at(t_us), truth)
    assert rmse < 0.02 * length
    # the first round's anchors sit where they did: the new poses carried into its frame
    before, after = one.meta.trajectory.at(anchors), two.meta.trajectory.at(anchors)
    scale = np.linalg.norm(before[-1, :3, 3] - before[0, :3, 3])
    assert np.abs(after[:, :3, 3] - before[:, :3, 3]).max() < 0.05 * scale
    assert np.abs(after[:, :3, :3] - before[:, :3, :3]).max() < 0.05


def test_a_round_of_three_anchors_of_a_still_camera_trains_the_real_preset_on_one_pose(scene, tmp_path):
    rec, _ = scene
    config = LearnConfig(workdir=tmp_path, intrinsics=(60.0, 60.0, 31.5, 23.5), preset="auto",
                         overrides=TINY, anchor_fps=10.0, min_anchors=3, first_steps=5, publish_s=1e9,
                         eval_frames=1)
    stream, outbox = Stream(W, H), _Outbox()
    learner = Learner(config, stream, outbox)
    t0 = int(rec.anchors.t_us[0])
    _feed(stream, rec, t0, t0 + 250_000)
    while not outbox:
        assert learner.step()
    # three small frames register too few (said on the learner's output) or show no parallax
    assert outbox[-1]["camera"] in ("still", "estimated: still") and outbox[-1]["preset"] == "real"
    published = load_checkpoint(outbox[-1]["path"])
    assert len(np.unique(published.meta.trajectory.c2w, axis=0)) == 1
    # the real preset's windows: what the published model holds is every row current, momentum paid
    trainer = learner.round.trainer
    assert trainer.model.windowed
    state = trainer.optimizer.state[trainer.model.gaussians.means]
    assert bool((state["row_step"] == state["step"]).all())
    assert torch.equal(published.gaussians.means, trainer.model.gaussians.means.detach())


def test_renders_beside_the_learner_take_the_cores_it_leaves(monkeypatch):
    """A render's numba threads on the learner's core wait on it (street3d, 2 cores: 9.2 ms a render on two
    threads, 5.5 on one), so a cold start rasterizes on the cores the learner leaves, at least one."""
    from edmcgs.server import service

    for cores, learner, expected in ((2, 1, 1), (16, 1, 15), (16, 4, 12), (1, 1, 1), (2, 3, 1)):
        monkeypatch.setattr(service.os, "sched_getaffinity", lambda _pid, n=cores: set(range(n)))
        assert service.beside_learner(learner) == expected
