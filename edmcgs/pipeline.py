"""From a recording to what the model trains on: the application layer's one adapter.

Every command (``edmcgs train``, ``edmcgs eval``), the server and the benchmarks turn a recording into
the model's plain arrays and config here; the model never sees the sensor's types, the sensor never the
model's.
"""

from __future__ import annotations

import sys

import numpy as np

from edmcgs.errors import TrainingError
from edmcgs.geometry import Intrinsics, Trajectory
from edmcgs.model.config import EdmcgsConfig, preset
from edmcgs.model.motion.leanness import events_decision
from edmcgs.model.train.data import TrainingData
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import Recording

STRUCTURAL = ("events", "markov", "sh_degree", "num_control_points", "skin_k", "graph_k", "deform_width",
              "deform_depth", "pos_freqs", "time_freqs", "event_pos_freqs", "event_hidden")
"""Config fields that shape the parameters: a resumed run cannot change them."""


def recording_intrinsics(rec: Recording) -> Intrinsics:
    """The recording's pinhole camera; without one, a centred camera with a 53-degree horizontal view."""
    if rec.intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in rec.intrinsics)
        return Intrinsics(fx, fy, cx, cy, rec.width, rec.height)
    print("warning: the recording has no intrinsics; assuming fx = fy = width, centred principal point",
          file=sys.stderr)
    return Intrinsics(float(rec.width), float(rec.width), (rec.width - 1) / 2, (rec.height - 1) / 2,
                      rec.width, rec.height)


def training_data(rec: Recording) -> TrainingData:
    """Turn a recording into the model's arrays; poses default to the trajectory, then to a static camera."""
    anchors = rec.anchors
    if len(anchors) == 0:
        raise TrainingError("the recording has no anchor frames: EdMCGS needs at least one RGB/APS frame")
    if (anchors.width, anchors.height) != (rec.width, rec.height):
        raise TrainingError("anchor frames and events differ in resolution; resample the frames first")
    if rec.trajectory_t_us is not None:
        trajectory = Trajectory(rec.trajectory_t_us, rec.trajectory_c2w)
    elif anchors.poses is not None:
        trajectory = Trajectory(anchors.t_us, anchors.poses)
    else:
        trajectory = Trajectory(anchors.t_us[:1], np.eye(4)[None])
    poses = anchors.poses if anchors.poses is not None else trajectory.at(anchors.t_us)
    ends = [int(anchors.t_us[-1])]
    if len(rec.events):
        ends.append(int(rec.events.t_end) + 1)
    held = rec.held_out
    if held is not None and len(held):
        ends.append(int(held.t_us[-1]))
    width, height, events = rec.width, rec.height, rec.events

    def event_map(t0_us: int, t1_us: int) -> np.ndarray:
        return accumulate(events.time_slice(t0_us, t1_us), width, height)

    return TrainingData(
        anchors_t_us=anchors.t_us, anchor_images=anchors.images, anchor_poses=poses,
        intrinsics=recording_intrinsics(rec), trajectory=trajectory, t_end_us=max(ends),
        event_map=event_map if len(events) else None, event_size=(width, height),
        held_out_t_us=None if held is None or not len(held) else held.t_us,
        held_out_images=None if held is None or not len(held) else held.images,
        held_out_poses=None if held is None or not len(held) else held.poses)


def build_config(name: str, overrides: list[str], rec: Recording) -> EdmcgsConfig:
    """Preset, then what the recording states (contrast threshold, a synthetic scene's constant
    background colour), then ``--set`` overrides, then what the data leaves out (no events: no event
    branch, said on stdout)."""
    cfg = preset(name)
    if rec.contrast_threshold is not None:
        cfg = cfg.replace(contrast_threshold=float(rec.contrast_threshold))
    background = rec.metadata.get("background")
    if isinstance(background, list) and len(background) == 3:
        cfg = cfg.replace(background=tuple(float(v) for v in background))
    cfg = cfg.with_overrides(overrides)
    events, message = events_decision(len(rec.events), cfg.events)
    if message is not None:
        print(f"edmcgs train: {message}")
        cfg = cfg.replace(events=events)
    return cfg
