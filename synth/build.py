"""``edmcgs synth``: build a synthetic recording from a procedural scene.

Timeline (scene time t in [0, duration], stored as int64 µs from 0):

- events: simulated over the whole span from renders at adaptive time steps (``esim``);
- anchors: sparse RGB frames at ``fps`` (t = k / fps), optionally motion-blurred with a 0.5 shutter;
- held-out: ``held_out_per_interval`` ground-truth frames evenly spaced inside each anchor interval
  (sharp; for evaluation);
- poses of every frame, and a dense camera trajectory (every ``TRAJECTORY_STEP_US``);
- the IMU a DAVIS346 on that camera would read (``synth.davis.simulated_imu``: 1 kHz, its noise and a
  bias per axis drawn from ``seed``; the scenes' worlds are z up).

The shutter of the blur is relative to the dense frame sequence that anchors and held-out frames
sample (fps * (held_out_per_interval + 1) frames per second), as when sparse frames are kept from a
high-frame-rate render: exposure = 0.5 / (fps * (held_out_per_interval + 1)), centred on the anchor,
averaged over ``BLUR_SUBFRAMES`` sub-frames in linear intensity. Frames store the rendered linear
colour as uint8 (no gamma), the quantity the simulator's luminance is computed from.
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
from edmcgs.luminance import LUMA
from edmcgs.sensor.files.recording import Recording, write_recording
from edmcgs.sensor.frames import Frames
from edmcgs.synth.davis import ImuConfig, simulated_imu
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig, simulate_render
from edmcgs.synth.scene import CAMERAS, SCENES, SIZES, Scene, make_scene, render

GENERATOR = "edmcgs.synth.build/1"
SHUTTER = 0.5
BLUR_SUBFRAMES = 8
TRAJECTORY_STEP_US = 2000
MAX_DELTA = 2.0  # bisect a simulation step while some pixel would fire more than 2 events in it


@dataclass(frozen=True)
class BuildConfig:
    """Everything that determines a synthetic recording (stored in its metadata)."""

    scene: str
    """One of ``edmcgs.synth.scene.SCENES``."""
    fps: float = 5.0
    """Anchor frame rate; the paper uses 5 and 10 (about 10 and 20 anchors over 2 s)."""
    size: str = "small"
    """"small" (173x130, fewer Gaussians) or "full" (346x260, the DAVIS346 resolution)."""
    seed: int = 0
    """Seeds the simulator's threshold mismatch and noise (the scenes themselves are deterministic)."""
    blur: bool = False
    """Motion-blur the anchor frames with a 0.5 shutter (see the module docstring)."""
    held_out_per_interval: int = 4
    """Ground-truth frames between two consecutive anchors."""
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    """Event simulator settings (its seed is replaced by ``seed``)."""
    sampling: AdaptiveSampling = field(default_factory=lambda: AdaptiveSampling(
        dt_max_us=4000, dt_min_us=250, max_delta=MAX_DELTA))
    """Adaptive render steps of the simulation: a step is halved while a pixel would fire more than two
    events in it (down to 250 µs); at most 4 ms."""
    duration_s: float | None = None
    """Length of the sequence; None: the scene's own (2 s). The scenes are defined at any t."""
    camera: str = "orbit"
    """Past the scene's own duration its camera circles on ("orbit") or sweeps back over the same arc
    ("sweep"); ``synth.scene.CAMERAS``. Within it both are the same."""
    imu: ImuConfig = field(default_factory=ImuConfig)
    """The IMU on the camera."""

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise InvalidInputError(f"scene {self.scene!r} is unknown; choose one of {', '.join(SCENES)}")
        if self.size not in SIZES:
            raise InvalidInputError(f"size {self.size!r} is unknown; choose one of {', '.join(SIZES)}")
        if not (math.isfinite(self.fps) and 0 < self.fps <= 1000):
            raise InvalidInputError(f"fps must be in (0, 1000], got {self.fps!r}")
        if not (isinstance(self.held_out_per_interval, int) and 0 <= self.held_out_per_interval <= 100):
            raise InvalidInputError(
                f"held_out_per_interval must be in 0..100, got {self.held_out_per_interval!r}")
        if self.duration_s is not None and not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise InvalidInputError(f"duration_s must be positive, got {self.duration_s!r}")
        if self.camera not in CAMERAS:
            raise InvalidInputError(f"camera {self.camera!r} is unknown; choose one of {', '.join(CAMERAS)}")
        if int(self.seed) != self.seed or self.seed < 0:
            raise InvalidInputError(f"seed must be a non-negative integer, got {self.seed!r}")


def _to_us(t_s) -> np.ndarray:
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e6).astype(np.int64)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)


def frame_times(duration_s: float, fps: float, held_out_per_interval: int) -> tuple[np.ndarray, np.ndarray]:
    """(anchor_t_us [F], held_out_t_us [(F - 1) * n]) over [0, duration_s]."""
    anchors_s = np.arange(math.floor(duration_s * fps + 1e-9) + 1) / fps
    if len(anchors_s) < 2:
        raise InvalidInputError(f"fps={fps} gives fewer than 2 anchors over {duration_s} s")
    n = held_out_per_interval
    frac = np.arange(1, n + 1) / (n + 1)
    held_s = (anchors_s[:-1, None] + frac[None, :] / fps).ravel()
    return _to_us(anchors_s), _to_us(held_s)


def _render_frames(scene: Scene, t_us: np.ndarray, exposure_us: int, bar: tqdm) -> Frames:
    images, poses = [], []
    for t in t_us:
        if exposure_us > 0:
            offsets = (np.arange(BLUR_SUBFRAMES) + 0.5) / BLUR_SUBFRAMES - 0.5
            sub = [render(scene, (t + o * exposure_us) * 1e-6) for o in offsets]
            image = np.mean(sub, axis=0)
        else:
            image = render(scene, t * 1e-6)
        images.append(_to_uint8(image))
        poses.append(scene.camera_at(t * 1e-6))
        bar.update(1)
    return Frames(t_us, np.stack(images), np.stack(poses))


def build_recording(config: BuildConfig, *, progress: bool = True) -> Recording:
    """Render, simulate and assemble the recording described by ``config``."""
    started = time.perf_counter()
    scene = make_scene(config.scene, config.size, config.camera)
    sim_config = SimulatorConfig(**(asdict(config.simulator) | {"seed": int(config.seed)}))
    intr = scene.intrinsics
    duration_s = scene.duration_s if config.duration_s is None else config.duration_s
    duration_us = int(_to_us(duration_s))
    anchor_t, held_t = frame_times(duration_s, config.fps, config.held_out_per_interval)
    dense_rate = config.fps * (config.held_out_per_interval + 1)
    exposure_us = round(SHUTTER / dense_rate * 1e6) if config.blur else 0

    label = f"{config.scene} {config.size} {config.fps:g} fps"
    with tqdm(total=len(anchor_t) + len(held_t), desc=f"{label}: frames", unit="frame",
              disable=not progress, file=sys.stderr) as bar:
        anchors = _render_frames(scene, anchor_t, exposure_us, bar)
        held_out = _render_frames(scene, held_t, 0, bar) if len(held_t) else None
    fmt = "{l_bar}{bar}| {n:.0f}/{total:.0f} ms scene time [{elapsed}]"
    with tqdm(total=duration_us / 1000, desc=f"{label}: events", disable=not progress, file=sys.stderr,
              bar_format=fmt) as bar:
        events, samples = simulate_render(lambda t: render(scene, t * 1e-6), 0, duration_us, sim_config,
                                          config.sampling, progress=lambda dt: bar.update(dt / 1000))

    traj_t = np.arange(0, duration_us + 1, TRAJECTORY_STEP_US, dtype=np.int64)
    traj_c2w = np.stack([scene.camera_at(t * 1e-6) for t in traj_t])
    imu, imu_metadata = scene_imu(scene, duration_us, config.imu, config.seed)
    n_gaussians = len(scene.gaussians_at(0.0))
    metadata = {
        "generator": GENERATOR,
        "scene": config.scene,
        "size": config.size,
        "fps": config.fps,
        "seed": int(config.seed),
        "duration_s": duration_s,
        "camera": config.camera,
        "held_out_per_interval": config.held_out_per_interval,
        "gaussians": n_gaussians,
        "background": list(scene.background),
        "blur": {"enabled": config.blur, "shutter": SHUTTER, "exposure_us": exposure_us,
                 "subframes": BLUR_SUBFRAMES if config.blur else 1},
        "simulator": sim_config.to_metadata() | {"luma_weights": list(LUMA),
                                                  "log": "L = log(luminance + eps) of the float render "
                                                         "(linear RGB in [0, 1]), before uint8"},
        "sampling": asdict(config.sampling) | {"samples": len(samples),
                                               "mean_step_us": float(np.diff(samples).mean())},
        "frames": "linear RGB of the render, uint8, no gamma",
        "imu": imu_metadata,
        "build_seconds": round(time.perf_counter() - started, 3),
    }
    return Recording(
        width=intr.width, height=intr.height, events=events, anchors=anchors, held_out=held_out,
        intrinsics=np.array([intr.fx, intr.fy, intr.cx, intr.cy]), trajectory_t_us=traj_t,
        trajectory_c2w=traj_c2w, contrast_threshold=sim_config.contrast_threshold, sensor="simulated",
        metadata=metadata, imu=imu)


def scene_imu(scene: Scene, duration_us: int, config: ImuConfig, seed: int) -> tuple[np.ndarray, dict]:
    """``synth.davis.simulated_imu`` along the scene's camera (samples, metadata entry)."""
    return simulated_imu(lambda ts: np.stack([scene.camera_at(float(t)) for t in ts]), duration_us, config,
                         seed)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="edmcgs synth", description=(
        "Build a synthetic dynamic scene with simulated events, sparse RGB anchors and held-out "
        "ground-truth frames, as an HDF5 recording. `edmcgs synth traffic|traffic-pan --help`: the "
        "composited street scene, a DAVIS346-like recording; `edmcgs synth street3d --help`: a 3D street "
        "seen by a handheld DAVIS346, with its IMU and a second camera's novel views."))
    p.add_argument("scene", choices=SCENES)
    p.add_argument("--fps", type=float, default=5.0, help="anchor frame rate (the paper: 5 or 10; default 5)")
    p.add_argument("-o", "--output", type=Path, help="output file (default: SCENE_FPSfps_SIZE.h5)")
    p.add_argument("--seed", type=int, default=0, help="seed of threshold mismatch and noise (default 0)")
    p.add_argument("--size", choices=sorted(SIZES), default="small",
                   help="small: 173x130, fewer Gaussians; full: 346x260 (default small)")
    p.add_argument("--duration", type=float, help="sequence length in seconds (default: the scene's, 2 s)")
    p.add_argument("--blur", action="store_true", help="motion-blur the anchor frames (0.5 shutter)")
    p.add_argument("--camera", choices=CAMERAS, default="orbit",
                   help="past the scene's own 2 s: orbit circles on (to views never seen in them), sweep "
                        "pans back over the same arc (default orbit)")
    p.add_argument("--held-out", type=int, default=4,
                   help="ground-truth frames per anchor interval (default 4)")
    p.add_argument("--contrast-threshold", type=float, default=0.2, help="C (default 0.2)")
    p.add_argument("--threshold-sigma", type=float, default=0.0,
                   help="per-pixel threshold mismatch, log units (default 0)")
    p.add_argument("--refractory-us", type=int, default=0, help="refractory period, µs (default 0)")
    p.add_argument("--noise-hz", type=float, default=0.0,
                   help="background events per pixel per second (default 0)")
    p.add_argument("--dt-min-us", type=int, default=250, help="finest simulation step, µs (default 250)")
    p.add_argument("--dt-max-us", type=int, default=4000, help="coarsest simulation step, µs (default 4000)")
    p.add_argument("--compress", action="store_true",
                   help="gzip the event columns (about 5x smaller, slower replay; for shipped files)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    """``edmcgs synth`` for the scenes drawn as Gaussians (``synth/cli.py`` dispatches by scene)."""
    args = _parser().parse_args(argv)
    try:
        simulator = SimulatorConfig(contrast_threshold=args.contrast_threshold,
                                    threshold_sigma=args.threshold_sigma, refractory_us=args.refractory_us,
                                    noise_rate_hz=args.noise_hz)
        config = BuildConfig(scene=args.scene, fps=args.fps, size=args.size, seed=args.seed, blur=args.blur,
                             held_out_per_interval=args.held_out, simulator=simulator,
                             duration_s=args.duration, camera=args.camera, sampling=AdaptiveSampling(
                                 dt_max_us=args.dt_max_us, dt_min_us=args.dt_min_us, max_delta=MAX_DELTA))
        out = args.output or Path(f"{args.scene}_{args.fps:g}fps_{args.size}.h5")
        save(build_recording(config, progress=not args.quiet), out, compress=args.compress)
    except EdmcgsError as exc:
        print(f"edmcgs synth: error: {exc}", file=sys.stderr)
        return 2
    return 0


def save(rec: Recording, out: Path, *, compress: bool) -> None:
    """Write a synthetic recording (gzip the events when ``compress``) and say what it holds."""
    write_recording(out, rec, compression="gzip" if compress else None)
    meta = rec.metadata
    gaussians = f"{meta['gaussians']} Gaussians, " if "gaussians" in meta else ""
    held = 0 if rec.held_out is None else len(rec.held_out)
    print(f"{out}: {meta['scene']} {rec.width}x{rec.height}, {gaussians}{meta['duration_s']:g} s, "
          f"{len(rec.anchors)} anchors, {held} held-out frames, {len(rec.events)} events "
          f"({meta['sampling']['samples']} renders), {meta['build_seconds']:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
