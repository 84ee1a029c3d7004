"""The report's synthetic recordings: built once with ``edmcgs.synth.build`` and cached as HDF5 under the
report folder; lower anchor rates are derived from the highest one.

Deriving is exact: events, held-out frames and anchors of a scene do not depend on each other, so the
recording at fps / k equals the one at fps with every k-th anchor kept and the others moved to the
held-out frames (the held-out frames of a build at fps / k with (n + 1) k - 1 frames per interval).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from bench.report.settings import ReportSettings
from edmcgs.sensor.files.recording import Recording, read_recording, write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.build import BuildConfig, build_recording
from edmcgs.synth.esim import AdaptiveSampling

MAX_DELTA = 2.0
"""The builder's bisection criterion (events per pixel per simulation step)."""


def build_config(scene: str, fps: float, s: ReportSettings) -> BuildConfig:
    return BuildConfig(scene=scene, fps=fps, size=s.size, duration_s=s.duration_s,
                       held_out_per_interval=s.held_out_per_interval,
                       sampling=AdaptiveSampling(dt_max_us=s.dt_max_us, dt_min_us=s.dt_min_us,
                                                 max_delta=MAX_DELTA))


def config_key(cfg: BuildConfig) -> str:
    """A file name that changes whenever anything in ``cfg`` does."""
    fields = asdict(cfg)
    if fields["camera"] == "orbit":  # the default of a later field: earlier keys stay valid
        del fields["camera"]
    digest = hashlib.sha1(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:10]
    return f"{cfg.scene}_{cfg.fps:g}fps_{cfg.size}_{digest}"


def cached_build(cfg: BuildConfig, cache: Path, *, progress: bool = True) -> tuple[Recording, str]:
    """The recording of ``cfg`` and its cache key, built and written to ``cache`` on first use."""
    key = config_key(cfg)
    path = cache / f"{key}.h5"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        write_recording(path, build_recording(cfg, progress=progress))
    return read_recording(path), key


def fewer_anchors(rec: Recording, every: int) -> Recording:
    """Keep every ``every``-th anchor (the first and, as in a build, the last one included); the dropped
    anchors join the held-out frames."""
    if every == 1:
        return rec
    if rec.metadata.get("blur", {}).get("enabled"):
        raise ValueError("blurred anchors differ from sharp held-out frames: build this rate directly")
    anchors = rec.anchors
    if (len(anchors) - 1) % every:
        raise ValueError(f"{len(anchors)} anchors cannot be thinned by {every}")
    kept = np.arange(len(anchors)) % every == 0
    held = rec.held_out
    t = np.concatenate([held.t_us, anchors.t_us[~kept]])
    order = np.argsort(t, kind="stable")
    held_out = Frames(t[order], np.concatenate([held.images, anchors.images[~kept]])[order],
                      np.concatenate([held.poses, anchors.poses[~kept]])[order])
    meta = dict(rec.metadata)
    meta["fps"] = rec.metadata["fps"] / every
    meta["held_out_per_interval"] = (rec.metadata["held_out_per_interval"] + 1) * every - 1
    meta["derived"] = f"every {every}th anchor of the {rec.metadata['fps']:g} fps recording"
    return Recording(width=rec.width, height=rec.height, events=rec.events,
                     anchors=Frames(anchors.t_us[kept], anchors.images[kept], anchors.poses[kept]),
                     held_out=held_out, intrinsics=rec.intrinsics, trajectory_t_us=rec.trajectory_t_us,
                     trajectory_c2w=rec.trajectory_c2w, contrast_threshold=rec.contrast_threshold,
                     sensor=rec.sensor, metadata=meta)


def scene_recordings(scene: str, rates: list[float], s: ReportSettings, cache: Path, *,
                     progress: bool = True) -> dict[float, tuple[Recording, str]]:
    """fps -> (recording, cache key) for every rate in ``rates``; one simulation per scene where the rates
    divide the highest one."""
    base_fps = max(rates)
    base, base_key = cached_build(build_config(scene, base_fps, s), cache, progress=progress)
    out = {}
    for fps in rates:
        every = round(base_fps / fps)
        if math.isclose(base_fps / fps, every) and (len(base.anchors) - 1) % every == 0:
            out[fps] = (fewer_anchors(base, every), f"{base_key}_every{every}")
        else:
            out[fps] = cached_build(build_config(scene, fps, s), cache, progress=progress)
    return out
