"""Camera poses from the frames and the IMU together: structure from motion's poses refined by the
camera's gyroscope and accelerometer (``edmcgs poses`` and ``--poses auto`` on a recording with IMU
samples, e.g. a DAVIS346's).

Structure from motion follows what it matched: where the scene itself moves (a figure that fills the
frame), its poses take on that motion. The IMU measures the camera's own motion, but drifts: a gyro's
bias turns an integrated rotation by degrees over seconds, an accelerometer's bias moves an integrated
position by metres. Both are combined in a batch least squares over every registered frame, in two steps:

1. rotations: the gyro's rotation between successive frames (preintegrated, its bias estimated) against
   each frame's rotation from structure from motion. Where the bias those rotations imply is one the
   part would not have, or one the frames' own steps between successive frames rule out (``DRIFT_CHI2``),
   the frames drift: structure from motion trades turning for translation when it follows a small or
   moving subject (jumpingjack's orbit falls 24 degrees short of an 80 degree turn, at a steady rate that
   a gyro bias of 6 deg/s would also explain, and no sensor here tells the two apart), and a close car
   that drives along with the camera bends its map (street3d at 30 s: 17 to 21 degrees over 4 s, a bias of
   0.9 deg/s in the joint fit, where the frames' steps put it within 0.01 deg/s of the true one). The
   bias is then estimated from the steps alone, each step's error independent (a drift spread over many
   steps is weak evidence of a bias, a bend over a few steps none), with the part's prior, and the
   rotations are the gyro's;
2. (optional, ``adjust``) the frames' positions estimated again with their rotations held at step 1's
   (a bundle adjustment by the caller: the translation a drifting rotation had pulled along comes back);
3. positions: the accelerometer's velocity and position increments between successive frames
   (preintegrated in the rotations of step 1), with the gravity vector, the accelerometer's bias and the
   metric scale of structure from motion's units estimated, against each frame's position.

Each step weighs the frames by their own scatter about the fit, re-estimated from the residuals (with a
Huber loss): where structure from motion follows the camera to a millimetre (a still street) the frames
decide; where it follows a moving figure, the IMU decides within seconds and the frames beyond. The IMU's
axes are taken to be the camera's rotated by ``imu_to_camera`` when a calibration gives it, else by the
rotation that best maps the gyro's rates onto the frames' (when the camera turned about two axes or
more; else the camera's own axes). An IMU that cannot help raises ``ImuUnusable`` naming why (it misses
part of the frames' span, its rates disagree with the frames', the camera hardly accelerated); the
caller keeps the frames' poses and says so.

Noise model: white noise at the densities of a DAVIS346's IMU class (MPU-6500: gyro 0.01 deg/s/sqrt(Hz),
accelerometer 300 ug/sqrt(Hz)) and a constant bias per axis over the recording (no random walk: a bias
that wanders over minutes is absorbed by the frames' weight), with a prior from the part's turn-on
tolerance (``GYRO_BIAS``, ``ACCEL_BIAS``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from edmcgs.errors import InvalidInputError, PoseEstimationError
from edmcgs.geometry import nearest_rotation, rotation_exp, rotation_log

STANDARD_GRAVITY = 9.80665
"""m/s^2 per g (the IMU's accelerometer unit)."""
GYRO_DENSITY = np.radians(0.01)
"""Gyro white noise, rad/s/sqrt(Hz)."""
ACCEL_DENSITY = 300e-6 * STANDARD_GRAVITY
"""Accelerometer white noise, m/s^2/sqrt(Hz)."""
ACCEL_BIAS = 0.05 * STANDARD_GRAVITY
"""Prior standard deviation of the accelerometer's bias per axis, m/s^2 (an MPU-6500-class part's turn-on
offset is up to 60 mg): without it a bias along an axis the camera never turned is indistinguishable
from gravity and the frames' own error."""
GYRO_BIAS = np.radians(5.0 / 3)
"""Prior standard deviation of the gyro's bias per axis, rad/s: an MPU-6500-class part's initial zero-rate
tolerance, +-5 deg/s, taken as three standard deviations (OKVIS's default, 0.03 rad/s, is the same). It
decides the bias only where the frames say little of it."""
DRIFT_CHI2 = 7.81
"""Chi-square, 3 degrees of freedom, 5 %: the frames' rotations drift when the gyro bias they imply as they
stand lies this far (squared, in standard deviations of ``GYRO_BIAS``) from zero: a bias the part would
not have; or this far (squared, in the standard deviations of the stepwise estimate) from the bias their
steps between successive frames imply: frames whose steps agree with the gyro to hundredths of a degree
but whose rotations as they stand call for another bias have bent somewhere. A lower level of the first
test would flag a large but genuine bias on frames whose steps are as noisy as the steps themselves (a
moving figure at video rates): those steps recover little of it, and its whole integral would be lost;
the second test weighs the steps by their own scatter, so noisy steps seldom pass it. A drift below both
is kept (jumpingjack's orbit: up to 1.2 % of the path, against 0.3 to 0.7 % with the gyro's rotations)."""
NEAREST_M = 0.05
"""Smallest median scene depth, metres, the position step accepts (the poses' unit is the median depth of
the scene, as ``edmcgs.poses`` makes it): nothing a DAVIS346's lens focuses on is nearer. Where the camera
circles at a steady rate the accelerometer cannot tell its motion from a bias and a still camera, and a
fit at a vanishing scale copies the frames at no cost."""
SCALE_STARTS = 2.0 ** np.arange(-8, 9)
"""Starts of the position step's scale, as factors of the windowed estimate (``_initial_scale``, which can
be 60 times off on an orbit): its iterations settle in the basin they start in, and the fit that explains
both sensors best is kept."""
NO_SCALE = "the IMU's motion does not fit the frames' at any positive scale"
MOUNT_SPAN_S = 0.5
"""Span over which the gyro's rotations and the frames' are compared to estimate the IMU's mounting."""
MAX_GAP_S = 0.05
"""Longest gap between IMU samples inside the frames' span."""
MAX_SCATTER = 0.8
"""Largest RMS angle between the frames' rotations and the fused ones, as a fraction of how much the frames
turn (RMS about their mean, once that is ``MIN_TURN_DEG`` or more): more, and the gyro is not this
camera's, or its axes are not as assumed. Structure from motion that follows a moving figure scatters by
a quarter to two thirds of the turning on jumpingjack (the IMU is there to remove that), so only a gross
mismatch is caught here."""
MIN_TURN_DEG = 5.0
"""Turning (RMS angle of the frames' rotations about their mean) below which ``MAX_SCATTER`` is not
checked: a camera that hardly turns says little of its gyro."""
HUBER = 2.0
"""Residuals beyond this many standard deviations weigh linearly (a kink, a frame that slipped)."""
TUKEY = 5.0
"""Steps between frames this many standard deviations (per axis) off the gyro's weigh nothing in its
stepwise bias (``_stepwise_bias``)."""
ROUNDS = 30
"""Most times a step re-estimates the frames' scatter (and the position step gravity's direction) and
solves again; it stops once the scale moves by less than ``CONVERGED``."""
CONVERGED = 1e-4


class ImuUnusable(PoseEstimationError):
    """The IMU samples cannot refine these poses (the message says why)."""


@dataclass(frozen=True)
class InertialFit:
    """Poses refined by the IMU, and what the fit estimated."""

    c2w: np.ndarray
    """float64 [F, 4, 4]: the frames' camera-to-world poses, in structure from motion's world and units."""
    gyro_bias_dps: np.ndarray
    """float64 [3]: the gyro's bias, degrees/s, in the IMU's axes."""
    accel_bias_g: np.ndarray
    """float64 [3]: the accelerometer's bias, g, in the IMU's axes."""
    gravity: np.ndarray
    """float64 [3]: the unit vector of gravity (down) in the world."""
    metres_per_unit: float
    """The metric size of one unit of the poses."""
    imu_to_camera: np.ndarray
    """float64 [3, 3]: rotation taking IMU axes to the camera's."""
    rotation_scatter_deg: float
    """RMS angle between the frames' rotations from structure from motion and the fit."""
    position_scatter: float
    """RMS distance between the frames' positions from structure from motion and the fit (units)."""
    frames_drift_dps: float | None = None
    """Where the frames' rotations drift against the gyro: the rate (deg/s) at which they do, a bias their
    rotations alone would have given the gyro; None where they do not."""

    def summary(self) -> str:
        drift = "" if self.frames_drift_dps is None else (
            f"; the frames' rotations drift by {self.frames_drift_dps:.1f} deg/s against the gyro: its "
            "rotations kept")
        return (f"IMU fused (the frames' poses scatter {self.rotation_scatter_deg:.2f} deg and "
                f"{self.position_scatter:.4f} units about it; 1 unit = {self.metres_per_unit:.3f} m; gyro "
                f"bias {np.linalg.norm(self.gyro_bias_dps):.2f} deg/s{drift})")


def fuse_imu(t_us, c2w, imu, *, imu_to_camera: np.ndarray | None = None,
             adjust: Callable[[np.ndarray], np.ndarray] | None = None) -> InertialFit:
    """``c2w`` (float64 [F, 4, 4], camera-to-world from structure from motion at ``t_us``, int64 [F]
    strictly increasing) refined by ``imu`` (``IMU_DTYPE`` samples: g, degrees/s, on the frames' clock).
    ``imu_to_camera``: the IMU's mounting (rotation [3, 3]), estimated from the rates when None.
    ``adjust``: given the fused rotations (c2w [F, 3, 3]), the frames' positions [F, 3] estimated again
    with them held (in ``c2w``'s world and units); None keeps ``c2w``'s positions.
    Raises ``ImuUnusable`` when the IMU cannot refine them."""
    t_us, c2w = _checked(t_us, c2w)
    t_s = (t_us - t_us[0]) * 1e-6
    gyro, force, sample_s = _samples(imu, t_us)
    vision_R, vision_p = c2w[:, :3, :3], c2w[:, :3, 3]
    seg = _segments(sample_s, t_s)
    if imu_to_camera is None:
        imu_to_camera = _mounting(seg, gyro, vision_R)
    mount = np.asarray(imu_to_camera, np.float64)
    if mount.shape != (3, 3) or not np.allclose(mount.T @ mount, np.eye(3), atol=1e-4):
        raise InvalidInputError("imu_to_camera must be a 3x3 rotation")
    gyro_c, force_c = gyro @ mount.T, force @ mount.T
    R, gyro_bias = _rotations(seg, gyro_c, vision_R)
    drift = None
    stepwise, information = _stepwise_bias(seg, gyro_c, vision_R)
    gap = gyro_bias - stepwise
    if (np.sum((gyro_bias / GYRO_BIAS) ** 2) > DRIFT_CHI2
            or gap @ information @ gap > DRIFT_CHI2):  # the frames drift
        drift = float(np.degrees(np.linalg.norm(gap)))
        gyro_bias = stepwise
    pre = _preintegrate(seg, gyro_c - gyro_bias, force_c)
    if drift is not None:
        R = _chained(pre.dR, vision_R)
    rot_scatter = _rms_angle(vision_R, R)
    spread = _rms_angle(nearest_rotation(vision_R.sum(0))[None], vision_R)  # the frames' turning
    if spread > np.radians(MIN_TURN_DEG) and rot_scatter > MAX_SCATTER * spread:
        raise ImuUnusable(f"the gyro's rotations differ from the frames' by {np.degrees(rot_scatter):.1f} "
                          f"deg RMS, against {np.degrees(spread):.1f} deg of turning (another camera's IMU, "
                          "or axes other than assumed)")
    if adjust is not None:
        vision_p = np.asarray(adjust(R), np.float64)
        if vision_p.shape != (len(t_us), 3) or not np.all(np.isfinite(vision_p)):
            raise ImuUnusable("the frames' positions could not be estimated again with the gyro's rotations")
    fit = _positions(pre, R, vision_p, t_s)
    c2w_out = np.tile(np.eye(4), (len(t_us), 1, 1))
    c2w_out[:, :3, :3] = R
    c2w_out[:, :3, 3] = fit.positions
    if not np.all(np.isfinite(c2w_out)):
        raise ImuUnusable("the fit did not converge to finite poses")
    return InertialFit(
        c2w=c2w_out, gyro_bias_dps=np.degrees(mount.T @ gyro_bias), accel_bias_g=mount.T @ fit.accel_bias /
        STANDARD_GRAVITY, gravity=fit.gravity / STANDARD_GRAVITY, metres_per_unit=fit.metres_per_unit,
        imu_to_camera=mount, rotation_scatter_deg=float(np.degrees(rot_scatter)),
        position_scatter=fit.scatter, frames_drift_dps=drift)


def _checked(t_us, c2w) -> tuple[np.ndarray, np.ndarray]:
    t_us, c2w = np.asarray(t_us), np.asarray(c2w, dtype=np.float64)
    if t_us.ndim != 1 or t_us.dtype.kind not in "iu":
        raise InvalidInputError(f"t_us must be 1-D integer microseconds, got {t_us.dtype} {t_us.shape}")
    if c2w.shape != (len(t_us), 4, 4) or not np.all(np.isfinite(c2w)):
        raise InvalidInputError(f"c2w must be finite [{len(t_us)}, 4, 4], got {c2w.shape}")
    if len(t_us) < 3:
        raise ImuUnusable(f"{len(t_us)} registered frames: the IMU needs at least 3")
    if np.any(np.diff(t_us) <= 0):
        raise InvalidInputError("frame times must be strictly increasing")
    return t_us.astype(np.int64), c2w


def _samples(imu, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gyro rad/s [K, 3], specific force m/s^2 [K, 3], sample times s [K]) of the samples covering the
    frames' span, relative to the first frame."""
    fields = getattr(getattr(imu, "dtype", None), "fields", None) or {}
    if not isinstance(imu, np.ndarray) or imu.ndim != 1 or not {"t", "gyro", "accel"} <= set(fields):
        raise InvalidInputError(f"imu must be a 1-D array of IMU samples (fields t, gyro, accel: the sensor "
                                f"layer's IMU_DTYPE), got {getattr(imu, 'dtype', type(imu))}")
    ok = np.isfinite(imu["gyro"]).all(1) & np.isfinite(imu["accel"]).all(1)
    imu = imu[ok][np.argsort(imu["t"][ok], kind="stable")]
    span = (t_us[-1] - t_us[0]) * 1e-6
    if len(imu) < 2:
        raise ImuUnusable(f"{len(imu)} IMU samples over the frames' {span:.1f} s")
    t = imu["t"]
    keep = (t >= t_us[0] - MAX_GAP_S * 1e6) & (t <= t_us[-1] + MAX_GAP_S * 1e6)
    imu, t = imu[keep], t[keep]
    covered = 0.0 if len(t) < 2 else min(t[-1], t_us[-1]) - max(t[0], t_us[0])
    gaps = np.diff(t) * 1e-6 if len(t) > 1 else np.array([np.inf])
    if len(t) < 2 or t[0] > t_us[0] + MAX_GAP_S * 1e6 or t[-1] < t_us[-1] - MAX_GAP_S * 1e6:
        raise ImuUnusable(f"the IMU covers {max(covered, 0) * 1e-6:.1f} of the {span:.1f} s the frames span")
    if gaps.max() > MAX_GAP_S:
        raise ImuUnusable(f"the IMU has a gap of {gaps.max():.2f} s within the frames' span")
    return (np.radians(imu["gyro"].astype(np.float64)),
            imu["accel"].astype(np.float64) * STANDARD_GRAVITY, (imu["t"] - t_us[0]) * 1e-6)


@dataclass(frozen=True)
class _Segments:
    """The frames' span cut at every frame and at the midpoints between IMU samples: each piece lies in
    one frame interval and is covered by one sample (a sample is the mean over its period)."""

    interval: np.ndarray
    """int64 [S]: the frame interval (i: from frame i to i + 1) of each piece."""
    sample: np.ndarray
    """int64 [S]: the sample that covers it."""
    dt: np.ndarray
    """float64 [S]: its length, s."""
    frame_dt: np.ndarray
    """float64 [F - 1]: the intervals' lengths."""


def _segments(sample_s: np.ndarray, t_s: np.ndarray) -> _Segments:
    cuts = np.unique(np.concatenate([t_s, 0.5 * (sample_s[1:] + sample_s[:-1])]))
    cuts = cuts[(cuts >= t_s[0]) & (cuts <= t_s[-1])]
    start, stop = cuts[:-1], cuts[1:]
    keep = stop > start
    start, stop = start[keep], stop[keep]
    mid = 0.5 * (start + stop)
    nearest = np.clip(np.searchsorted(sample_s, mid), 1, len(sample_s) - 1)
    nearest -= (mid - sample_s[nearest - 1]) < (sample_s[nearest] - mid)
    interval = np.clip(np.searchsorted(t_s, mid) - 1, 0, len(t_s) - 2)
    return _Segments(interval, nearest, stop - start, np.diff(t_s))


@dataclass(frozen=True)
class _Preintegrated:
    """Per frame interval, in the camera's axes at its first frame: the rotation to its last (dR), the
    velocity and position increments of the specific force (dv, dp), their derivatives with respect to the
    accelerometer's bias (jv, jp: [F - 1, 3, 3]) and to the gyro's bias (jr, of dR's rotation vector)."""

    dR: np.ndarray
    dv: np.ndarray
    dp: np.ndarray
    jv: np.ndarray
    jp: np.ndarray
    jr: np.ndarray
    dt: np.ndarray


def _preintegrate(seg: _Segments, gyro: np.ndarray, force: np.ndarray) -> _Preintegrated:
    """Every interval at once: its pieces are applied in turn, the k-th piece of all intervals together."""
    n = len(seg.frame_dt)
    rank = np.arange(len(seg.interval)) - np.searchsorted(seg.interval, seg.interval)
    dR, dv, dp = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros((n, 3))
    jv, jp, jr = np.zeros((n, 3, 3)), np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    for k in range(int(rank.max()) + 1 if len(rank) else 0):
        pick = rank == k
        i, s, dt = seg.interval[pick], seg.sample[pick], seg.dt[pick]
        R = dR[i]
        step = rotation_exp(gyro[s] * dt[:, None])
        a = np.einsum("nij,nj->ni", R, force[s])
        dp[i] += dv[i] * dt[:, None] + 0.5 * a * dt[:, None] ** 2
        dv[i] += a * dt[:, None]
        jp[i] += jv[i] * dt[:, None, None] - 0.5 * R * dt[:, None, None] ** 2
        jv[i] -= R * dt[:, None, None]
        # d(rotation vector of dR)/d(gyro bias), to first order: each piece's rotation carried to the end
        jr[i] = np.swapaxes(step, 1, 2) @ jr[i] - dt[:, None, None] * np.eye(3)
        dR[i] = R @ step
    return _Preintegrated(dR, dv, dp, jv, jp, jr, seg.frame_dt)


def _mounting(seg: _Segments, gyro: np.ndarray, vision_R: np.ndarray) -> np.ndarray:
    """The rotation from IMU to camera axes that best maps the gyro's rotations onto the frames' own over
    spans of ``MOUNT_SPAN_S`` (long enough that the turning outweighs the frames' jitter; Kabsch, the
    gyro's bias estimated alongside). The camera's own axes (the identity) unless the frames turn about
    two axes or more and the estimate explains them at least twice as well."""
    n = len(vision_R)
    span = int(np.clip(round(MOUNT_SPAN_S / np.median(seg.frame_dt)), 1, max(1, n - 2)))
    frames = rotation_log(np.swapaxes(vision_R[:-span], 1, 2) @ vision_R[span:])
    seconds = np.convolve(seg.frame_dt, np.ones(span), "valid")

    def spans(bias):
        dR = _preintegrate(seg, gyro - bias, np.zeros_like(gyro)).dR
        chained = dR[:n - span].copy()
        for k in range(1, span):
            chained = chained @ dR[k:n - span + k]
        return rotation_log(chained)

    mount, bias = np.eye(3), np.zeros(3)
    for _ in range(4):
        imu = spans(bias)
        u, sv, vt = np.linalg.svd(frames.T @ imu)
        if sv[1] < 0.1 * sv[0]:
            return np.eye(3)
        mount = nearest_rotation(u @ vt)
        bias = bias + ((imu - frames @ mount) * seconds[:, None]).sum(0) / (seconds**2).sum()
    misfit = np.linalg.norm(frames - imu @ mount.T, axis=1).sum()
    as_is = np.linalg.norm(frames - imu, axis=1).sum()
    return mount if misfit < 0.5 * as_is else np.eye(3)


def _rms_angle(a: np.ndarray, b: np.ndarray) -> float:
    """RMS angle between the rotations a and b ([F or 1, 3, 3] each), rad."""
    return float(np.sqrt(np.mean(np.sum(rotation_log(np.swapaxes(a, 1, 2) @ b) ** 2, axis=1))))


def _robust_rms(r: np.ndarray) -> float:
    """RMS of the 3-vectors r [N, 3], from their median norm (a few outliers do not inflate it)."""
    return float(np.median(np.linalg.norm(r, axis=1))) / 1.538 if len(r) else 0.0  # chi(3)'s median


def _solve(rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]],
           unknowns: int) -> np.ndarray:
    """The x minimising the sum over residual blocks (3 rows each, whitened) of |J x + c|^2, or of
    huber(|J x + c|) for the kinds marked robust: iteratively reweighted least squares. ``rows``: per
    kind of residual, (row, column, value) of J's entries, c, robust; rows counted within the kind."""
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import spsolve

    offset, r_all, c_all, v_all, const, robust = 0, [], [], [], [], []
    for r, c, v, k, huber in rows:
        r_all.append(r + offset)
        c_all.append(c)
        v_all.append(v)
        const.append(k)
        robust.append(np.full(len(k), huber))
        offset += len(k)
    J = coo_matrix((np.concatenate(v_all), (np.concatenate(r_all), np.concatenate(c_all))),
                   shape=(offset, unknowns)).tocsr()
    c, robust = np.concatenate(const), np.concatenate(robust)
    weights = np.ones(offset)
    x = np.zeros(unknowns)
    for _ in range(20):
        x = spsolve((J.T @ diags(weights) @ J).tocsc(), -(J.T @ (weights * c)))
        norms = np.repeat(np.linalg.norm((J @ x + c).reshape(-1, 3), axis=1), 3)
        new = np.where(robust & (norms > HUBER), HUBER / np.maximum(norms, 1e-12), 1.0)
        if np.allclose(new, weights, atol=1e-3):
            break
        weights = new
    return x


def _joined(parts: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """(row, column, value) triples of several blocks' entries, concatenated into one."""
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))


def _blocks(first: np.ndarray, column: np.ndarray, matrices: np.ndarray) -> tuple[np.ndarray, ...]:
    """(row, column, value) of the 3xC blocks ``matrices`` [N, 3, C] of a sparse matrix: block ``k`` in
    rows 3 first[k] .. 3 first[k] + 2, columns column[k] .. column[k] + C - 1."""
    i, j = np.meshgrid(np.arange(3), np.arange(matrices.shape[2]), indexing="ij")
    return (3 * first[:, None, None] + i).ravel(), (column[:, None, None] + j).ravel(), matrices.ravel()


def _rotations(seg: _Segments, gyro: np.ndarray, vision_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(fused c2w rotations [F, 3, 3], gyro bias rad/s [3] in camera axes). Gauss-Newton on a small rotation
    per frame (R <- R Exp(e)) and the bias."""
    n = len(vision_R)
    R, bias = vision_R.copy(), np.zeros(3)
    sigma_vision = np.radians(0.5)
    eye = np.tile(np.eye(3), (n, 1, 1))
    k = np.arange(n - 1)
    for _ in range(3):
        pre = _preintegrate(seg, gyro - bias, np.zeros_like(gyro))
        sigma = (GYRO_DENSITY * np.sqrt(pre.dt) + 1e-6)[:, None, None]
        step_bias = np.zeros(3)
        for _ in range(5):
            expected = pre.dR @ rotation_exp(np.einsum("nij,j->ni", pre.jr, step_bias))
            between = rotation_log(np.swapaxes(expected, 1, 2) @ np.swapaxes(R[:-1], 1, 2) @ R[1:])
            off = rotation_log(np.swapaxes(vision_R, 1, 2) @ R)
            gyro_rows = [_blocks(k, 3 * k, -(np.swapaxes(R[1:], 1, 2) @ R[:-1]) / sigma),
                         _blocks(k, 3 * k + 3, eye[1:] / sigma),
                         _blocks(k, np.full(n - 1, 3 * n), -pre.jr / sigma)]
            gyro_part = _joined(gyro_rows)
            vision_part = _blocks(np.arange(n), 3 * np.arange(n), eye / sigma_vision)
            prior = _blocks(np.zeros(1, np.int64), np.array([3 * n]), np.eye(3)[None] / GYRO_BIAS)
            x = _solve([(*gyro_part, (between / sigma[:, :, 0]).ravel(), False),
                        (*vision_part, (off / sigma_vision).ravel(), True),
                        (*prior, (bias + step_bias) / GYRO_BIAS, False)], 3 * n + 3)
            R = R @ rotation_exp(x[:3 * n].reshape(n, 3))
            step_bias = step_bias + x[3 * n:]
            if np.abs(x).max() < 1e-9:
                break
        bias = bias + step_bias
        sigma_vision = max(_robust_rms(rotation_log(np.swapaxes(vision_R, 1, 2) @ R)), np.radians(0.01))
    return R, bias


def _stepwise_bias(seg: _Segments, gyro: np.ndarray, vision_R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gyro's bias (rad/s [3] in camera axes) from the frames' rotations between successive frames
    alone (each step's error independent) and the prior ``GYRO_BIAS``, with its information [3, 3] (the
    inverse of its covariance):
    Gauss-Newton, weighted by Tukey's biweight (a run of steps where the frames' map bent counts for
    nothing, where Huber's weights would still spread its bend over the bias), the steps' scatter
    re-estimated."""
    steps = np.swapaxes(vision_R[:-1], 1, 2) @ vision_R[1:]
    bias, sigma = np.zeros(3), np.radians(0.5)
    prior = np.eye(3) / GYRO_BIAS**2
    for _ in range(20):
        pre = _preintegrate(seg, gyro - bias, np.zeros_like(gyro))
        r = rotation_log(np.swapaxes(pre.dR, 1, 2) @ steps)  # r(bias + d) ~ r - jr d
        norm = np.linalg.norm(r, axis=1) / sigma
        w = np.clip(1.0 - (norm / TUKEY) ** 2, 0.0, None) ** 2 / sigma**2
        normal = np.einsum("n,nji,njk->ik", w, pre.jr, pre.jr) + prior
        d = np.linalg.solve(normal, np.einsum("n,nji,nj->i", w, pre.jr, r) - prior @ bias)
        bias = bias + d
        sigma = max(_robust_rms(r), np.radians(0.01))
        if np.abs(d).max() < 1e-9:
            break
    return bias, normal


def _chained(dR: np.ndarray, vision_R: np.ndarray) -> np.ndarray:
    """The rotations [F, 3, 3] chained from the steps ``dR`` [F - 1, 3, 3], turned as a whole onto
    ``vision_R`` (least squares)."""
    R = np.tile(np.eye(3), (len(vision_R), 1, 1))
    for i, step in enumerate(dR):
        R[i + 1] = R[i] @ step
    return nearest_rotation(np.einsum("nij,nkj->ik", vision_R, R)) @ R


@dataclass(frozen=True)
class _PositionFit:
    """What the position step made of the accelerometer and the frames' positions."""

    positions: np.ndarray
    """float64 [F, 3], in the frames' units."""
    metres_per_unit: float
    gravity: np.ndarray
    """m/s^2 [3] in the world."""
    accel_bias: np.ndarray
    """m/s^2 [3] in camera axes."""
    scatter: float
    """RMS distance of the frames' positions from the fit (units)."""
    misfit: float
    """The IMU's whitened misfit plus the frames' at their jitter (the same for every start)."""


def _positions(pre: _Preintegrated, R: np.ndarray, vision_p: np.ndarray, t_s: np.ndarray) -> _PositionFit:
    """Of the fits started from each of ``SCALE_STARTS`` at a plausible scale, the one that explains both
    sensors best."""
    world_dp = np.einsum("nij,nj->ni", R[:-1], pre.dp)
    world_dv = np.einsum("nij,nj->ni", R[:-1], pre.dv)
    down = -world_dv.sum(0)  # the mean specific force balances gravity
    down /= max(np.linalg.norm(down), 1e-12)
    # the frames' jitter, from their second differences (a smooth path has next to none at video rates)
    jitter = max(_robust_rms(vision_p[2:] - 2 * vision_p[1:-1] + vision_p[:-2]) / np.sqrt(6), 1e-5)
    starts = _initial_scale(pre, world_dp, world_dv, vision_p, t_s, STANDARD_GRAVITY * down) * SCALE_STARTS
    fits = []
    for start in starts[starts >= NEAREST_M]:
        try:
            fit = _positions_from(pre, R, world_dp, world_dv, vision_p, jitter, down, start)
        except ImuUnusable:
            continue
        if fit.metres_per_unit >= NEAREST_M:
            fits.append(fit)
    if not fits:
        raise ImuUnusable(NO_SCALE)
    return min(fits, key=lambda fit: fit.misfit)


def _positions_from(pre: _Preintegrated, R: np.ndarray, world_dp: np.ndarray, world_dv: np.ndarray,
                    vision_p: np.ndarray, jitter: float, down: np.ndarray, scale: float) -> _PositionFit:
    """``_positions``' fit from a start: gravity along ``down`` (unit [3]), ``scale`` metres per unit;
    ``world_dp``, ``world_dv``: the increments turned into the world by R; ``jitter``: the frames'.

    Linear least squares in the units of structure from motion (the scale cannot collapse): each frame's
    position and velocity, and gravity, the accelerometer's bias and metres-to-units (lambda) times it
    (gravity * lambda, bias * lambda), so that the increments read lambda * (R dp + ...) stay linear. The
    IMU's rows are whitened by its noise in units (lambda of the previous solve); gravity's norm is held by
    a row along its previous direction. The misfit compares the frames at their jitter, the same for every
    start: the scatter the fit re-estimates would let a fit at a vanishing scale, where the IMU no longer
    constrains the positions, copy the frames and claim no error."""
    n = len(vision_p)
    k = np.arange(n - 1)
    dt = pre.dt[:, None, None]
    eye = np.tile(np.eye(3), (n - 1, 1, 1))
    lam, sigma_vision = 1.0 / scale, jitter
    Q, U, G, B, L = 0, 3 * n, 6 * n, 6 * n + 2, 6 * n + 5
    col = np.zeros(n - 1, np.int64)
    f = np.arange(n)
    lam_rows = (3 * k[:, None] + np.arange(3)).ravel()

    for _ in range(ROUNDS):
        previous = lam
        # gravity * lambda = lambda * g * down + T t, t the tilt (units/s^2) across the current direction
        T = np.linalg.svd(down[None])[2][1:].T  # [3, 2], orthonormal, across down
        sv = lam * (ACCEL_DENSITY * np.sqrt(dt) + 1e-5)
        sp = lam * (ACCEL_DENSITY * dt**1.5 / np.sqrt(3) + 1e-6)
        tilt = np.tile(T, (n - 1, 1, 1))
        position = _joined([
            _blocks(k, Q + 3 * k + 3, eye / sp), _blocks(k, Q + 3 * k, -eye / sp),
            _blocks(k, U + 3 * k, -eye * dt / sp), _blocks(k, col + G, -0.5 * tilt * dt**2 / sp),
            _blocks(k, col + B, -(R[:-1] @ pre.jp) / sp),
            (lam_rows, np.full(len(lam_rows), L),
             -((world_dp + 0.5 * STANDARD_GRAVITY * down * dt[:, :, 0]**2) / sp[:, :, 0]).ravel())])
        velocity = _joined([
            _blocks(k, U + 3 * k + 3, eye / sv), _blocks(k, U + 3 * k, -eye / sv),
            _blocks(k, col + G, -tilt * dt / sv), _blocks(k, col + B, -(R[:-1] @ pre.jv) / sv),
            (lam_rows, np.full(len(lam_rows), L), -((world_dv + STANDARD_GRAVITY * down * dt[:, :, 0])
                                                   / sv[:, :, 0]).ravel())])
        vision = _blocks(f, Q + 3 * f, np.tile(np.eye(3), (n, 1, 1)) / sigma_vision)
        prior = _blocks(np.zeros(1, np.int64), np.array([B]), np.eye(3)[None] / (lam * ACCEL_BIAS))
        x = _solve([(*position, np.zeros(3 * (n - 1)), False), (*velocity, np.zeros(3 * (n - 1)), False),
                    (*vision, (-vision_p / sigma_vision).ravel(), True), (*prior, np.zeros(3), False)],
                   6 * n + 6)
        positions, lam = x[:3 * n].reshape(n, 3), float(x[L])
        if not lam > 0:
            raise ImuUnusable(NO_SCALE)
        g = STANDARD_GRAVITY * down + T @ x[G:G + 2] / lam
        down = g / np.linalg.norm(g)
        sigma_vision = max(_robust_rms(positions - vision_p), 1e-5)
        if abs(lam / previous - 1) < CONVERGED:
            break
    off = np.sum((positions - vision_p) ** 2, axis=1)
    misfit = sum(_squares(*rows, x) for rows in (position, velocity, prior)) + float(off.sum()) / jitter**2
    return _PositionFit(positions, 1.0 / lam, STANDARD_GRAVITY * down, x[B:B + 3] / lam,
                        float(np.sqrt(off.mean())), misfit)


def _squares(row: np.ndarray, column: np.ndarray, value: np.ndarray, x: np.ndarray) -> float:
    """|J x|^2 of the sparse J given by its (row, column, value) entries."""
    return float(np.sum(np.bincount(row, weights=value * x[column]) ** 2))


def _initial_scale(pre: _Preintegrated, world_dp: np.ndarray, world_dv: np.ndarray, vision_p: np.ndarray,
                   t_s: np.ndarray, gravity: np.ndarray) -> float:
    """Metres per unit: over windows of about a second, the least-squares scale that fits the dead-reckoned
    positions (each window's start position and velocity free) to the frames'; their median, each window
    weighted by how far its dead reckoning bends from a straight line (how much it says of the scale).
    ``world_dp``, ``world_dv``: the increments turned into the world, without gravity's."""
    world_dp = world_dp + 0.5 * gravity * pre.dt[:, None] ** 2
    world_dv = world_dv + gravity * pre.dt[:, None]
    n = len(t_s)
    window = max(3, int(np.searchsorted(t_s, t_s[0] + 1.0)))
    scales, accel = [], []
    for start in range(0, n - 2, max(1, window // 2)):
        stop = min(n, start + window)
        if stop - start < 3:
            continue
        # dead reckoning with zero start velocity; the velocity enters as a free term v0 * (t - t0)
        v = np.vstack([np.zeros(3), np.cumsum(world_dv[start:stop - 1], axis=0)])
        steps = world_dp[start:stop - 1] + v[:-1] * pre.dt[start:stop - 1, None]
        q = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
        tau = t_s[start:stop] - t_s[start]
        # unknowns: s, p0 (3), v0 (3): s * vision = p0 + v0 tau + q
        k = stop - start
        A = np.zeros((3 * k, 7))
        A[:, 0] = vision_p[start:stop].ravel()
        for axis in range(3):
            A[axis::3, 1 + axis] = -1.0
            A[axis::3, 4 + axis] = -tau
        solution, *_ = np.linalg.lstsq(A, q.ravel(), rcond=None)
        curvature = q - np.polyval(np.polyfit(tau, q, 1), tau[:, None]) if k > 2 else q
        scales.append(solution[0])
        accel.append(float(np.sqrt(np.mean(curvature**2))))
    scales, accel = np.asarray(scales), np.asarray(accel)
    good = (scales > 0) & (accel > 0)
    if not good.any():
        raise ImuUnusable("the camera hardly accelerated: the IMU cannot tell the scale of its motion")
    weights = accel[good]
    order = np.argsort(scales[good])
    cumulative = np.cumsum(weights[order])
    return float(scales[good][order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
