"""The DAVIS346-like sensor of the street scenes (``traffic``, ``street3d``): APS readout, event pixels, IMU.

- APS: ``APS_HZ`` grey frames, each the mean of the sharp luminance over its exposure (``aps_frame``),
  plus Gaussian read noise, rounded to uint8 (``read_out``);
- events: the simulator settings of a DAVIS346 in daylight (``DAVIS346_SIMULATOR``);
- IMU: what a gyroscope and an accelerometer rigidly on the camera read along a camera path
  (``imu_truth``, from the poses alone), plus white noise and a constant bias per axis (``ImuConfig``,
  ``imu_samples``). Samples are the sensor layer's ``IMU_DTYPE`` (dv's units: g and degrees per second),
  in the camera frame (OpenCV: x right, y down, z forward): a level camera at rest reads accel (0, -1, 0) g.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import rotation_log
from edmcgs.sensor.imu import IMU_DTYPE
from edmcgs.synth.esim import AdaptiveSampling, SimulatorConfig

APS_HZ = 25.0
STANDARD_GRAVITY = 9.80665
"""m/s^2 per g."""

DAVIS346_SIMULATOR = SimulatorConfig(
    contrast_threshold=0.2, threshold_sigma=0.03, refractory_us=250, noise_rate_hz=0.2,
    hot_pixel_fraction=3e-4, hot_pixel_rate_hz=100.0)
"""Event-pixel settings of a DAVIS346 in daylight, and why:

- C = 0.2 (log units), the nominal threshold of DAVIS biases near their defaults (ESIM and v2e use
  0.2 too; the project's other scenes and the model's default assume it);
- threshold mismatch sigma = 0.03: v2e's default pixel-to-pixel spread, measured on DVS/DAVIS sensors
  at about 2-4 % contrast;
- refractory period 250 µs: DAVIS346 refractory biases give some 100 µs to 1 ms; a pixel under a
  fast edge (400 px/s, C = 0.2, a 1.5 log-unit edge fires ~7 events over 2.5 ms) loses about half
  of them, as real pixels do;
- background activity 0.2 Hz per pixel (18k events/s over 346x260): the leak/shot-noise rate of a
  DAVIS346 in normal indoor/outdoor light is 0.1 to 1 Hz per pixel;
- hot pixels: 3 per 10,000 pixels (27 at 346x260) firing 100 Hz each (2.7k events/s): the few
  pixels a DAVIS346 hot-pixel filter typically removes fire at tens to hundreds of Hz.
"""


def check_aps(fps: float, duration_s: float, exposure_us: int, subframes: int, read_noise_dn: float,
              simulator) -> None:
    """InvalidInputError unless these are a valid recording's APS and event settings."""
    if not (math.isfinite(fps) and 0 < fps <= APS_HZ):
        raise InvalidInputError(f"fps must be in (0, {APS_HZ:g}], got {fps!r}")
    ratio = APS_HZ / fps
    if abs(ratio - round(ratio)) > 1e-9:
        raise InvalidInputError(f"fps={fps:g} must divide the {APS_HZ:g} Hz APS rate "
                                "(25, 12.5, 5, 2.5, ...): anchors are every (25 / fps)-th frame")
    if not (math.isfinite(duration_s) and 0 < duration_s <= 600):
        raise InvalidInputError(f"duration_s must be in (0, 600], got {duration_s!r}")
    if not (isinstance(exposure_us, int) and 0 <= exposure_us < 1e6 / APS_HZ):
        raise InvalidInputError(f"exposure_us must be an integer in [0, 40000), got {exposure_us!r}")
    if not (isinstance(subframes, int) and 1 <= subframes <= 1000):
        raise InvalidInputError(f"subframes must be an integer in 1..1000, got {subframes!r}")
    if not (math.isfinite(read_noise_dn) and 0 <= read_noise_dn <= 64):
        raise InvalidInputError(f"read_noise_dn must be in [0, 64], got {read_noise_dn!r}")
    if not isinstance(simulator, SimulatorConfig):
        raise InvalidInputError("simulator must be a SimulatorConfig")


def held_out_per_interval(fps: float) -> int:
    """APS frames between two anchors at ``fps``."""
    return round(APS_HZ / fps) - 1


def add_recording_flags(p: argparse.ArgumentParser, defaults, *, name: str, seed_help: str) -> None:
    """The flags every DAVIS346-like scene's builder takes: its rate, length, size, seed and output, the
    APS readout, the event pixels and the simulation's steps, the output's compression and the progress
    bar. ``defaults``: the scene's config (fps, duration_s, exposure_us, read_noise_dn, sampling)."""
    p.add_argument("--fps", type=float, default=defaults.fps, help="anchor rate, dividing 25 (default 5)")
    p.add_argument("-o", "--output", type=Path, help=f"output file (default: {name}_FPSfps_SIZE.h5)")
    p.add_argument("--seed", type=int, default=0, help=f"seed of {seed_help} (default 0)")
    p.add_argument("--size", choices=("full", "small"), default="full",
                   help="full: 346x260, the DAVIS346 (default); small: 173x130")
    p.add_argument("--duration", "--seconds", type=float, default=defaults.duration_s,
                   help=f"sequence length in seconds (default {defaults.duration_s:g})")
    add_sensor_flags(p, exposure_us=defaults.exposure_us, read_noise_dn=defaults.read_noise_dn,
                     dt_min_us=defaults.sampling.dt_min_us, dt_max_us=defaults.sampling.dt_max_us)
    p.add_argument("--compress", action="store_true", help="gzip the event columns (smaller, slower replay)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def add_sensor_flags(p: argparse.ArgumentParser, *, exposure_us: int, read_noise_dn: float,
                     dt_min_us: int, dt_max_us: int) -> None:
    """The command-line flags of the APS readout, the event pixels and the simulation's steps."""
    s = DAVIS346_SIMULATOR
    p.add_argument("--exposure-us", type=int, default=exposure_us,
                   help=f"APS exposure, µs (default {exposure_us})")
    p.add_argument("--read-noise-dn", type=float, default=read_noise_dn,
                   help=f"APS read noise, 8-bit DN (default {read_noise_dn:g})")
    p.add_argument("--contrast-threshold", type=float, default=s.contrast_threshold, help="C (default 0.2)")
    p.add_argument("--threshold-sigma", type=float, default=s.threshold_sigma,
                   help=f"per-pixel threshold mismatch, log units (default {s.threshold_sigma:g})")
    p.add_argument("--refractory-us", type=int, default=s.refractory_us,
                   help=f"refractory period, µs (default {s.refractory_us})")
    p.add_argument("--noise-hz", type=float, default=s.noise_rate_hz,
                   help=f"background events per pixel per second (default {s.noise_rate_hz:g})")
    p.add_argument("--hot-pixels", type=float, default=s.hot_pixel_fraction,
                   help=f"fraction of hot pixels (default {s.hot_pixel_fraction:g})")
    p.add_argument("--hot-hz", type=float, default=s.hot_pixel_rate_hz,
                   help=f"events per second of each hot pixel (default {s.hot_pixel_rate_hz:g})")
    p.add_argument("--dt-min-us", type=int, default=dt_min_us,
                   help=f"finest simulation step, µs (default {dt_min_us})")
    p.add_argument("--dt-max-us", type=int, default=dt_max_us,
                   help=f"coarsest simulation step, µs (default {dt_max_us})")


def sensor_from_flags(args: argparse.Namespace) -> tuple[SimulatorConfig, AdaptiveSampling]:
    """The event pixels and the simulation's steps that ``add_sensor_flags``' flags set."""
    simulator = SimulatorConfig(
        contrast_threshold=args.contrast_threshold, threshold_sigma=args.threshold_sigma,
        refractory_us=args.refractory_us, noise_rate_hz=args.noise_hz,
        hot_pixel_fraction=args.hot_pixels, hot_pixel_rate_hz=args.hot_hz)
    return simulator, AdaptiveSampling(dt_max_us=args.dt_max_us, dt_min_us=args.dt_min_us, max_delta=2.0)


def aps_frame(render: Callable[[float], np.ndarray], t_us: int, exposure_us: int,
              subframes: int) -> np.ndarray:
    """The noise-free APS image at t_us: the mean of ``render(t_s)`` (a sharp luminance image, float64
    [H, W]) over the exposure centred on t_us, ``subframes`` samples."""
    if exposure_us == 0:
        return render(t_us * 1e-6)
    offsets = ((np.arange(subframes) + 0.5) / subframes - 0.5) * exposure_us
    return np.mean([render((t_us + o) * 1e-6) for o in offsets], axis=0)


def read_out(image: np.ndarray, read_noise_dn: float, rng: np.random.Generator) -> np.ndarray:
    """Digitise a [0, 1] luminance image: + N(0, read_noise_dn / 255), rounded and clipped to uint8."""
    dn = image * 255.0
    if read_noise_dn > 0:
        dn = dn + rng.normal(0.0, read_noise_dn, size=image.shape)
    return np.clip(np.round(dn), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class ImuConfig:
    """The IMU of a DAVIS346 (an InvenSense MPU-6500-class part), and why each default.

    rate_hz: 1 kHz, the DAVIS346's usual IMU rate. Noise per sample: the part's noise densities
    (gyro 0.01 deg/s/sqrt(Hz), accel 300 ug/sqrt(Hz)) over a ~100 Hz low-pass give about 0.1 deg/s and
    3 mg. Biases: a turn-on offset per axis, constant over a recording of seconds (an uncalibrated
    part: about 0.5 deg/s and 20 mg).
    """

    rate_hz: float = 1000.0
    gyro_noise_dps: float = 0.1
    """Standard deviation of each gyro sample's white noise, degrees per second."""
    accel_noise_g: float = 0.003
    """Standard deviation of each accelerometer sample's white noise, g."""
    gyro_bias_dps: float = 0.5
    """Standard deviation of the constant gyro bias drawn per axis for a recording, degrees per second."""
    accel_bias_g: float = 0.02
    """Standard deviation of the constant accelerometer bias drawn per axis, g."""
    temperature_c: float = 30.0
    """The temperature every sample reports."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 1 <= self.rate_hz <= 100_000):
            raise InvalidInputError(f"ImuConfig.rate_hz must be in [1, 100000], got {self.rate_hz!r}")
        for name in ("gyro_noise_dps", "accel_noise_g", "gyro_bias_dps", "accel_bias_g"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"ImuConfig.{name} must be a finite number >= 0, got {value!r}")
        if not math.isfinite(self.temperature_c):
            raise InvalidInputError(f"ImuConfig.temperature_c must be finite, got {self.temperature_c!r}")

    def to_metadata(self) -> dict:
        return asdict(self)


def imu_truth(pose_at: Callable[[np.ndarray], np.ndarray], t_s: np.ndarray,
              gravity=(0.0, 0.0, -STANDARD_GRAVITY)) -> tuple[np.ndarray, np.ndarray]:
    """(angular velocity rad/s, specific force m/s^2), float64 [K, 3] each, in the camera frame at t_s.

    pose_at(t [K]) -> camera-to-world [K, 4, 4], a smooth path in metres (twice differentiable);
    gravity: the world's gravity vector (z up: (0, 0, -g)). Each sample is the mean over its period (the
    spacing of t_s; an IMU's low-pass), by differences over it: the body rate from R(t - h/2)^T R(t + h/2),
    the acceleration from the positions at t - h, t, t + h (a triangle window of the acceleration). A
    path with a kink (a sweep that turns back) gives its velocity step in full, as a real IMU does; a
    smooth one is within O(h^2) of the instantaneous values.
    """
    t_s = np.asarray(t_s, np.float64)
    period = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1e-3
    hr, hp = 0.5 * period, period
    before, after = pose_at(t_s - hr), pose_at(t_s + hr)
    gyro = rotation_log(np.einsum("kji,kjl->kil", before[:, :3, :3], after[:, :3, :3])) / (2 * hr)
    now = pose_at(t_s)
    p = [pose_at(t_s + d)[:, :3, 3] for d in (-hp, hp)]
    accel_world = (p[0] - 2.0 * now[:, :3, 3] + p[1]) / (hp * hp)
    force = np.einsum("kji,kj->ki", now[:, :3, :3], accel_world - np.asarray(gravity, np.float64))
    return gyro, force


def imu_samples(t_us: np.ndarray, gyro_rad_s: np.ndarray, force_m_s2: np.ndarray, config: ImuConfig,
                rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """What the IMU reports for the true motion: IMU_DTYPE [K] (g, deg/s), and the biases drawn
    ({"gyro_dps": [3], "accel_g": [3]}, for the metadata)."""
    k = len(t_us)
    gyro_bias = rng.normal(0.0, config.gyro_bias_dps, 3)
    accel_bias = rng.normal(0.0, config.accel_bias_g, 3)
    out = np.empty(k, IMU_DTYPE)
    out["t"] = t_us
    out["gyro"] = np.degrees(gyro_rad_s) + gyro_bias + rng.normal(0.0, config.gyro_noise_dps, (k, 3))
    out["accel"] = force_m_s2 / STANDARD_GRAVITY + accel_bias + rng.normal(0.0, config.accel_noise_g, (k, 3))
    out["temperature"] = config.temperature_c
    return out, {"gyro_dps": gyro_bias.tolist(), "accel_g": accel_bias.tolist()}


def simulated_imu(pose_at: Callable[[np.ndarray], np.ndarray], duration_us: int, config: ImuConfig,
                  seed: int) -> tuple[np.ndarray, dict]:
    """What the IMU reads over [0, duration_us] on the camera path ``pose_at`` (c2w of a z-up world in
    metres; see ``imu_truth``): IMU_DTYPE samples at ``config.rate_hz``, and the recording metadata's
    "imu" entry (the config, the biases drawn, units and axes). ``seed``: the recording's."""
    t_us = np.arange(0, duration_us + 1, round(1e6 / config.rate_hz), dtype=np.int64)
    gyro, force = imu_truth(pose_at, t_us * 1e-6)
    imu, biases = imu_samples(t_us, gyro, force, config,
                              np.random.default_rng(np.random.SeedSequence([int(seed), 6])))
    return imu, config.to_metadata() | {
        "biases": biases, "units": "accel g, gyro degrees per second",
        "frame": "the camera's axes (OpenCV: x right, y down, z forward)",
        "gravity": "included: a level camera at rest reads accel (0, -1, 0)"}
