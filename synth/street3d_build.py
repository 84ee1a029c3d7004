"""``edmcgs synth street3d``: a DAVIS346-like recording of the 3D street (``synth.street3d``) seen by a
handheld camera, with its IMU and a second camera's novel views.

The sensor is ``synth traffic``'s (``synth.davis``): 25 Hz grey APS frames, each the mean of the sharp
luminance over its exposure plus read noise (every (25 / fps)-th an anchor, the others held out); events
from ``esim`` on the sharp luminance with threshold mismatch, refractory period, background activity and
hot pixels. Then what a moving camera adds:

- the true trajectory: every frame's pose and the dense trajectory every 2 ms (camera-to-world, OpenCV
  axes, metres), as the other synthetic scenes store them;
- the IMU (``/imu``): gyro and accelerometer at 1 kHz from the true motion (gravity included), with
  noise and a bias per axis, in the camera's axes;
- the novel views (``/novel_views``): the rig's second camera (``street3d.RIG``: 0.3 m to the left,
  turned 5 degrees right, the same intrinsics and sensor) at every held-out frame's time, its poses
  with them, for scoring views no anchor was taken from.

The simulation's steps: the walking camera moves the whole image, so every step sees some pixel
change; the default finest step is 1 ms (``synth traffic``: 0.25 ms; ``--dt-min-us`` sets it), and the
street without its cars is rendered every 4 ms and interpolated in between (``street3d.EventRender``),
the cars exactly at every step.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth import street3d
from edmcgs.synth.build import TRAJECTORY_STEP_US, frame_times, save
from edmcgs.synth.davis import (
    APS_HZ,
    DAVIS346_SIMULATOR,
    ImuConfig,
    add_recording_flags,
    aps_frame,
    check_aps,
    held_out_per_interval,
    read_out,
    sensor_from_flags,
    simulated_imu,
)
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig, simulate_render
from edmcgs.synth.street3d import KEYFRAME_US, RIG, EventRender, StreetScene

GENERATOR = "edmcgs.synth.street3d_build/1"
SIZES = {"small": (173, 130), "full": (street3d.FULL_WIDTH, street3d.FULL_HEIGHT)}


@dataclass(frozen=True)
class Street3dConfig:
    """Everything that determines a street3d recording (stored in its metadata)."""

    fps: float = 5.0
    """Anchor rate: every (25 / fps)-th APS frame is an anchor; 25 / fps must be a whole number."""
    duration_s: float = 4.0
    width: int = street3d.FULL_WIDTH
    height: int = street3d.FULL_HEIGHT
    seed: int = 0
    """Seeds the street, the traffic, the hand's motion, the read noise, the IMU and the simulator."""
    occupancy: float = 0.8
    """Probability that a lane's slot holds a car."""
    exposure_us: int = 10_000
    """APS exposure, centred on each frame's timestamp."""
    subframes: int = 5
    """Samples averaged over the exposure (a car at 300 px/s moves 0.6 px between two)."""
    read_noise_dn: float = 2.5
    """Standard deviation of the Gaussian read noise, 8-bit digital numbers."""
    simulator: SimulatorConfig = field(default_factory=lambda: DAVIS346_SIMULATOR)
    """Event pixel settings (its seed is replaced by ``seed``)."""
    sampling: AdaptiveSampling = field(default_factory=lambda: AdaptiveSampling(
        dt_max_us=4000, dt_min_us=1000, max_delta=2.0))
    """Adaptive render steps of the simulation (see the module docstring)."""
    keyframe_us: int = KEYFRAME_US
    """Interval of the street's renders the simulation interpolates between (``EventRender``)."""
    imu: ImuConfig = field(default_factory=ImuConfig)

    def __post_init__(self) -> None:
        check_aps(self.fps, self.duration_s, self.exposure_us, self.subframes, self.read_noise_dn,
                  self.simulator)
        if not isinstance(self.imu, ImuConfig):
            raise InvalidInputError("imu must be an ImuConfig")
        if isinstance(self.keyframe_us, bool) or not isinstance(self.keyframe_us, int) or \
                not 1 <= self.keyframe_us <= 40_000:
            raise InvalidInputError(f"keyframe_us must be an integer in 1..40000, got {self.keyframe_us!r}")
        StreetScene.check(self.width, self.height, self.seed, self.occupancy)

    @property
    def held_out_per_interval(self) -> int:
        return held_out_per_interval(self.fps)


def build_street3d(config: Street3dConfig, *, progress: bool = True) -> Recording:
    """Render, expose, read out and simulate the recording described by ``config``."""
    started = time.perf_counter()
    scene = StreetScene(config.width, config.height, seed=config.seed, occupancy=config.occupancy)
    sim_config = SimulatorConfig(**(asdict(config.simulator) | {"seed": int(config.seed)}))
    duration_us = round(config.duration_s * 1e6)
    anchor_t, held_t = frame_times(config.duration_s, config.fps, config.held_out_per_interval)
    all_t = np.sort(np.concatenate([anchor_t, held_t]))
    noise_rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), 3]))
    novel_rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), 4]))

    label = f"{scene.name} {scene.width}x{scene.height} {config.fps:g} fps"
    images, novel = {}, []
    with tqdm(total=len(all_t) + len(held_t), desc=f"{label}: frames", unit="frame", disable=not progress,
              file=sys.stderr) as bar:
        for t in all_t:  # in time order: a frame's read noise does not depend on the fps
            images[int(t)] = read_out(aps_frame(scene.render, int(t), config.exposure_us, config.subframes),
                                      config.read_noise_dn, noise_rng)
            bar.update(1)
        for t in held_t:
            novel.append(read_out(aps_frame(scene.render_novel, int(t), config.exposure_us, config.subframes),
                                  config.read_noise_dn, novel_rng))
            bar.update(1)

    def poses(ts: np.ndarray) -> np.ndarray:
        return scene.path.c2w(ts * 1e-6)

    def frames(ts: np.ndarray) -> Frames:
        return Frames(ts, np.stack([images[int(t)] for t in ts])[..., None], poses(ts))

    fmt = "{l_bar}{bar}| {n:.0f}/{total:.0f} ms scene time [{elapsed}]"
    render = EventRender(scene, config.keyframe_us)
    with tqdm(total=duration_us / 1000, desc=f"{label}: events", disable=not progress, file=sys.stderr,
              bar_format=fmt) as bar:
        events, samples = simulate_render(render, 0, duration_us, sim_config, config.sampling,
                                          progress=lambda dt: bar.update(dt / 1000))

    imu, imu_metadata = simulated_imu(scene.path.c2w, duration_us, config.imu, config.seed)
    traj_t = np.arange(0, duration_us + 1, TRAJECTORY_STEP_US, dtype=np.int64)
    intr = scene.intrinsics
    metadata = {
        "generator": GENERATOR,
        "scene": scene.name,
        "width": scene.width,
        "height": scene.height,
        "fps": config.fps,
        "aps_hz": APS_HZ,
        "seed": int(config.seed),
        "duration_s": config.duration_s,
        "held_out_per_interval": config.held_out_per_interval,
        "occupancy": config.occupancy,
        "world": "metres; x along the street (east), y across it (north), z up; the ground is z = 0",
        "lanes": [{"y": y, "direction": d, "speed_m_s": v, "period_s": p} for y, d, v, p in scene.lanes],
        "camera": {"walk": {k: [v[0], v[1], [list(w) for w in v[2]]] for k, v in street3d.WALK.items()},
                   "shake_m": [list(w) for w in street3d.SHAKE_M],
                   "shake_rad": [list(w) for w in street3d.SHAKE_RAD],
                   "channels": "offset, rate per s, (amplitude, Hz) sines; yaw, pitch, roll in radians"},
        "novel_views": {"rig": RIG.tolist(), "pose": "c2w(t) @ rig (the event camera's pose times the rig)",
                        "times": "the held-out frames' times", "intrinsics": "the recording's",
                        "aps": "the same exposure, read noise drawn on its own"},
        "imu": imu_metadata,
        "aps": {"exposure_us": config.exposure_us, "subframes": config.subframes,
                "read_noise_dn": config.read_noise_dn, "timestamp": "centre of the exposure"},
        "simulator": sim_config.to_metadata() | {"log": "L = log(luminance + eps) of the sharp float "
                                                         "luminance in [0, 1], before any readout"},
        "sampling": asdict(config.sampling) | {"samples": len(samples),
                                               "mean_step_us": float(np.diff(samples).mean()),
                                               "keyframe_us": config.keyframe_us,
                                               "keyframes": render.renders},
        "frames": "grey linear luminance, uint8, no gamma; exposure blur and read noise, held-out too",
        "build_seconds": round(time.perf_counter() - started, 3),
    }
    return Recording(
        width=scene.width, height=scene.height, events=events, anchors=frames(anchor_t),
        held_out=frames(held_t) if len(held_t) else None,
        intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]), trajectory_t_us=traj_t,
        trajectory_c2w=poses(traj_t), contrast_threshold=sim_config.contrast_threshold, sensor="simulated",
        metadata=metadata, imu=imu,
        novel_views=None if not len(held_t) else Frames(held_t, np.stack(novel)[..., None],
                                                        poses(held_t) @ RIG))


def _parser() -> argparse.ArgumentParser:
    d = Street3dConfig()
    p = argparse.ArgumentParser(prog="edmcgs synth street3d", description=(
        "Build the 3D street (ray-cast, not drawn by Gaussians) seen by a handheld DAVIS346: 25 Hz grey "
        "APS frames with exposure blur and read noise (anchors every 25/fps-th, the rest held out), "
        "simulated events with mismatch, refractory period, noise and hot pixels, IMU samples, the true "
        "trajectory, and a second camera's novel views at the held-out times."))
    p.add_argument("scene", choices=("street3d",))
    add_recording_flags(p, d, name="street3d", seed_help="the street, traffic, hand, noise, IMU and events")
    p.add_argument("--subframes", type=int, default=d.subframes,
                   help=f"renders averaged over each exposure (default {d.subframes})")
    p.add_argument("--imu-hz", type=float, default=d.imu.rate_hz, help="IMU sample rate (default 1000)")
    p.add_argument("--sheet", type=Path, help="also write a PNG contact sheet of the recording here")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        simulator, sampling = sensor_from_flags(args)
        width, height = SIZES[args.size]
        config = Street3dConfig(
            fps=args.fps, duration_s=args.duration, width=width, height=height, seed=args.seed,
            exposure_us=args.exposure_us, subframes=args.subframes, read_noise_dn=args.read_noise_dn,
            simulator=simulator, sampling=sampling, imu=ImuConfig(rate_hz=args.imu_hz))
        out = args.output or Path(f"street3d_{args.fps:g}fps_{args.size}.h5")
        rec = build_street3d(config, progress=not args.quiet)
        save(rec, out, compress=args.compress)
        if args.sheet is not None:
            from edmcgs.synth.sheet import contact_sheet

            contact_sheet(rec, args.sheet)
            print(f"{args.sheet}: contact sheet")
    except EdmcgsError as exc:
        print(f"edmcgs synth: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
