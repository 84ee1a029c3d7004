"""``edmcgs synth traffic``: a DAVIS346-like recording of the composited street (``synth.traffic``).

The camera is modelled, not just sampled:

- APS frames: grey (one channel, the format's C = 1), ``APS_HZ`` = 25 frames per second, each the mean
  of the sharp luminance over its ``exposure_us`` window centred on its timestamp (``subframes``
  samples: exposure blur), plus Gaussian read noise, rounded to uint8 (linear luminance, no gamma);
- events: ``esim`` on the *sharp* luminance (the pixels see the instantaneous scene, not the
  integrated APS frame), adaptive steps, with the DAVIS346-like non-idealities of ``DAVIS346_SIMULATOR``.

Every 25 Hz frame is stored: every (25 / fps)-th is an anchor (t = k / fps, as ``build.frame_times``),
the others are the held-out frames ``edmcgs eval`` scores, the camera's own noisy, blurred frames,
as with a real recording. Poses (identity, or the pan's rotation about y) come with every frame,
and the dense trajectory every 2 ms.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from edmcgs.errors import EdmcgsError, InvalidInputError
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.build import TRAJECTORY_STEP_US, frame_times, save
from edmcgs.synth.davis import (
    APS_HZ,
    DAVIS346_SIMULATOR,
    add_recording_flags,
    aps_frame,
    check_aps,
    held_out_per_interval,
    read_out,
    sensor_from_flags,
)
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig, simulate_render
from edmcgs.synth.traffic import FULL_HEIGHT, FULL_WIDTH, TrafficScene

GENERATOR = "edmcgs.synth.traffic_build/1"
SCENES = ("traffic", "traffic-pan")
SIZES = {"small": (173, 130), "full": (FULL_WIDTH, FULL_HEIGHT)}

@dataclass(frozen=True)
class TrafficConfig:
    """Everything that determines a traffic recording (stored in its metadata)."""

    pan: bool = False
    """Pan the camera (about its y axis) at ``pan_px_s``; else a static camera."""
    pan_px_s: float = 12.0
    """Pan speed at the image centre, full-resolution px/s (a slow pan: 36 px over 3 s)."""
    fps: float = 5.0
    """Anchor rate: every (25 / fps)-th APS frame is an anchor; 25 / fps must be a whole number."""
    duration_s: float = 3.0
    width: int = FULL_WIDTH
    height: int = FULL_HEIGHT
    seed: int = 0
    """Seeds the scene (layout, traffic), the read noise and the simulator."""
    occupancy: float = 0.85
    """Traffic density: probability that a lane's slot holds a car (about 2 cars per lane in view)."""
    exposure_us: int = 10_000
    """APS exposure, centred on each frame's timestamp (10 ms: a daylight street setting)."""
    subframes: int = 10
    """Samples averaged over the exposure (at 400 px/s: one every 0.4 px)."""
    read_noise_dn: float = 2.5
    """Standard deviation of the Gaussian read noise, in 8-bit digital numbers, added before rounding."""
    simulator: SimulatorConfig = field(default_factory=lambda: DAVIS346_SIMULATOR)
    """Event pixel settings (its seed is replaced by ``seed``)."""
    sampling: AdaptiveSampling = field(default_factory=lambda: AdaptiveSampling(
        dt_max_us=4000, dt_min_us=250, max_delta=2.0))
    """Adaptive render steps of the simulation (as ``edmcgs synth``'s scenes)."""

    def __post_init__(self) -> None:
        check_aps(self.fps, self.duration_s, self.exposure_us, self.subframes, self.read_noise_dn,
                  self.simulator)
        if not (math.isfinite(self.pan_px_s) and 0 < abs(self.pan_px_s) <= 200):
            raise InvalidInputError(f"pan_px_s must be non-zero, within +-200 px/s, got {self.pan_px_s!r}")
        TrafficScene(self.width, self.height, seed=self.seed, occupancy=self.occupancy)  # checks the rest

    @property
    def held_out_per_interval(self) -> int:
        return held_out_per_interval(self.fps)

    def scene(self) -> TrafficScene:
        return TrafficScene(self.width, self.height, pan_px_s=self.pan_px_s if self.pan else 0.0,
                            seed=self.seed, occupancy=self.occupancy)


def build_traffic(config: TrafficConfig, *, progress: bool = True) -> Recording:
    """Composite, expose, read out and simulate the recording described by ``config``."""
    started = time.perf_counter()
    scene = config.scene()
    sim_config = SimulatorConfig(**(asdict(config.simulator) | {"seed": int(config.seed)}))
    duration_us = round(config.duration_s * 1e6)
    anchor_t, held_t = frame_times(config.duration_s, config.fps, config.held_out_per_interval)
    all_t = np.sort(np.concatenate([anchor_t, held_t]))
    noise_rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), 3]))

    label = f"{scene.name} {scene.width}x{scene.height} {config.fps:g} fps"
    images = {}
    with tqdm(total=len(all_t), desc=f"{label}: frames", unit="frame", disable=not progress,
              file=sys.stderr) as bar:
        for t in all_t:  # in time order, so the read noise of a frame does not depend on the fps
            images[int(t)] = read_out(aps_frame(scene.render, int(t), config.exposure_us, config.subframes),
                                      config.read_noise_dn, noise_rng)
            bar.update(1)

    def frames(ts: np.ndarray) -> Frames:
        return Frames(ts, np.stack([images[int(t)] for t in ts])[..., None],
                      np.stack([scene.camera_at(t * 1e-6) for t in ts]))

    fmt = "{l_bar}{bar}| {n:.0f}/{total:.0f} ms scene time [{elapsed}]"
    with tqdm(total=duration_us / 1000, desc=f"{label}: events", disable=not progress, file=sys.stderr,
              bar_format=fmt) as bar:
        events, samples = simulate_render(lambda t: scene.render(t * 1e-6), 0, duration_us, sim_config,
                                          config.sampling, progress=lambda dt: bar.update(dt / 1000))

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
        "pan_px_s": scene.pan_px_s,
        "occupancy": config.occupancy,
        "lanes": [asdict(lane) for lane in scene.lanes],
        "aps": {"exposure_us": config.exposure_us, "subframes": config.subframes,
                "read_noise_dn": config.read_noise_dn, "timestamp": "centre of the exposure"},
        "simulator": sim_config.to_metadata() | {"log": "L = log(luminance + eps) of the sharp float "
                                                         "luminance in [0, 1], before any readout"},
        "sampling": asdict(config.sampling) | {"samples": len(samples),
                                               "mean_step_us": float(np.diff(samples).mean())},
        "frames": "grey linear luminance, uint8, no gamma; exposure blur and read noise, held-out too",
        "build_seconds": round(time.perf_counter() - started, 3),
    }
    return Recording(
        width=scene.width, height=scene.height, events=events, anchors=frames(anchor_t),
        held_out=frames(held_t) if len(held_t) else None,
        intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]), trajectory_t_us=traj_t,
        trajectory_c2w=np.stack([scene.camera_at(t * 1e-6) for t in traj_t]),
        contrast_threshold=sim_config.contrast_threshold, sensor="simulated", metadata=metadata)


def _parser() -> argparse.ArgumentParser:
    d = TrafficConfig()
    p = argparse.ArgumentParser(prog="edmcgs synth", description=(
        "Build the composited street scene (not drawn by Gaussians) as a DAVIS346-like recording: "
        "25 Hz grey APS frames with exposure blur and read noise (anchors every 25/fps-th, the rest "
        "held out) and simulated events with mismatch, refractory period, noise and hot pixels."))
    p.add_argument("scene", choices=SCENES, help="traffic: static camera; traffic-pan: a slow pan")
    p.add_argument("--pan", action="store_true", help="pan the camera (the same as traffic-pan)")
    p.add_argument("--pan-px-s", type=float, default=d.pan_px_s,
                   help=f"pan speed at the image centre, px/s at 346x260 (default {d.pan_px_s:g})")
    add_recording_flags(p, d, name="SCENE", seed_help="the scene, read noise and events")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        simulator, sampling = sensor_from_flags(args)
        width, height = SIZES[args.size]
        config = TrafficConfig(
            pan=args.pan or args.scene == "traffic-pan", pan_px_s=args.pan_px_s, fps=args.fps,
            duration_s=args.duration, width=width, height=height, seed=args.seed,
            exposure_us=args.exposure_us, read_noise_dn=args.read_noise_dn, simulator=simulator,
            sampling=sampling)
        name = "traffic-pan" if config.pan else "traffic"
        out = args.output or Path(f"{name}_{args.fps:g}fps_{args.size}.h5")
        save(build_traffic(config, progress=not args.quiet), out, compress=args.compress)
    except EdmcgsError as exc:
        print(f"edmcgs synth: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
