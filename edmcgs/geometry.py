"""Geometry shared by every layer: pinhole cameras, OpenCV-convention poses and their checks, projection,
wire parsing of poses, trajectories, and quaternion algebra (numpy and differentiable torch).

Conventions: a pose is a camera-to-world 4x4 float64 numpy array (OpenCV: x right, y down, z
forward); quaternions are (w, x, y, z); pixel centres sit at integer coordinates (pixel (row i,
column j) is at u = j, v = i), so a centred principal point is cx = (width - 1) / 2. Time is int64
microseconds; interpolation weights are computed in float64 from int64 differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from edmcgs.errors import InvalidInputError, PoseError

ROTATION_ATOL = 1e-3
"""Largest |R^T R - I| entry a pose may have; covers rotations printed with 4-5 decimals."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an undistorted image."""

    fx: float
    """Focal length along x, pixels (> 0)."""
    fy: float
    """Focal length along y, pixels (> 0)."""
    cx: float
    """Principal point x, pixels, in the integer-pixel-centre convention."""
    cy: float
    """Principal point y, pixels, in the integer-pixel-centre convention."""
    width: int
    """Image width, pixels (>= 1)."""
    height: int
    """Image height, pixels (>= 1)."""

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise InvalidInputError(f"intrinsics.{name} must be a number, got {type(value).__name__}")
            if not math.isfinite(value):
                raise InvalidInputError(f"intrinsics.{name} must be finite, got {value}")
            object.__setattr__(self, name, float(value))
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise InvalidInputError(f"intrinsics.{name} must be > 0, got {getattr(self, name)}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InvalidInputError(f"intrinsics.{name} must be an integer >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera sampled at another resolution (e.g. 346x260 -> 173x130).

        Pixel edges, not centres, scale: u + 0.5 maps to s * (u + 0.5).
        """
        if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or width < 1:
            raise InvalidInputError(f"width must be an integer >= 1, got {width!r}")
        if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 1:
            raise InvalidInputError(f"height must be an integer >= 1, got {height!r}")
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
                          int(width), int(height))

    def matrix(self) -> np.ndarray:
        """K: float64 [3, 3]."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------- rotations

def quat_multiply(a, b):
    """Hamilton product a * b (rotation b first, then a), in the type given.

    a, b: [..., 4] (w, x, y, z), broadcastable. Tensors: the differentiable algebra of the deformation
    path, returns Tensor. Anything else (array-like): returns np.ndarray float64.
    """
    if isinstance(a, Tensor):
        (aw, ax, ay, az), (bw, bx, by, bz), stack = a.unbind(-1), b.unbind(-1), torch.stack
    else:
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        (aw, ax, ay, az), (bw, bx, by, bz), stack = np.moveaxis(a, -1, 0), np.moveaxis(b, -1, 0), np.stack
    return stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """q / |q|; a zero quaternion becomes the identity instead of NaN."""
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    return torch.where(norm > eps, q / norm.clamp_min(eps), identity)


def rotmat_entries(w, x, y, z) -> tuple:
    """The 9 entries (row-major) of the rotation of a unit quaternion, for numpy, torch and numba alike."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def _quat_to_rotmat_torch(q: Tensor) -> Tensor:
    """Rotation matrices of unit quaternions (differentiable).

    q: Tensor  # [..., 4] (w, x, y, z), unit norm
    returns Tensor  # [..., 3, 3]
    """
    return torch.stack(rotmat_entries(*q.unbind(-1)), dim=-1).reshape(*q.shape[:-1], 3, 3)


def quat_to_rotmat(q):
    """Rotation matrices of quaternions, in the type given.

    A torch Tensor  # [..., 4] unit norm (w, x, y, z): the differentiable algebra of the deformation
    path, returns Tensor [..., 3, 3] of its dtype, nothing checked. Anything else (array-like
    [..., 4]): normalised here, a zero or non-finite quaternion is a PoseError; returns np.ndarray
    [..., 3, 3] float64.
    """
    if isinstance(q, Tensor):
        return _quat_to_rotmat_torch(q)
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise PoseError(f"quaternion must have 4 components (w, x, y, z), got shape {q.shape}")
    if not np.isfinite(q).all():
        raise PoseError("quaternion has a non-finite component")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if (norm < 1e-12).any():
        raise PoseError("quaternion has zero norm; it describes no rotation")
    # numpy here: a pose lookup is a handful of quaternions, where torch's per-op overhead dominates
    return np.stack(rotmat_entries(*np.moveaxis(q / norm, -1, 0)), axis=-1).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(R) -> np.ndarray:
    """Unit quaternions (w >= 0) of rotation matrices (Shepperd's method, stable for every angle).

    R: array-like  # [..., 3, 3] rotation matrices
    returns np.ndarray  # [..., 4] float64 (w, x, y, z)
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise PoseError(f"rotation must be 3x3, got shape {R.shape}")
    if not np.isfinite(R).all():
        raise PoseError("rotation has a non-finite entry")
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    diag = np.diagonal(m, axis1=1, axis2=2)
    # Pick the largest of 4w^2, 4x^2, 4y^2, 4z^2 to divide by, so no case loses precision.
    cand = np.stack([tr, 2 * diag[:, 0] - tr, 2 * diag[:, 1] - tr, 2 * diag[:, 2] - tr], axis=1)
    k = np.argmax(cand, axis=1)
    s = np.sqrt(np.maximum(1.0 + cand[np.arange(len(m)), k], 1e-300)) * 2.0  # 4 * the largest component
    q = np.empty((len(m), 4))
    w_ = (m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1])
    x_ = (m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1])
    rows = {
        0: (0.25 * s, w_[0] / s, w_[1] / s, w_[2] / s),
        1: (w_[0] / s, 0.25 * s, x_[0] / s, x_[1] / s),
        2: (w_[1] / s, x_[0] / s, 0.25 * s, x_[2] / s),
        3: (w_[2] / s, x_[1] / s, x_[2] / s, 0.25 * s),
    }
    for case, comps in rows.items():
        sel = k == case
        q[sel] = np.stack([c[sel] for c in comps], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(*R.shape[:-2], 4)


# --------------------------------------------------------------------------------------------- poses

def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of rotation vectors [..., 3] (Rodrigues), float64."""
    w = np.asarray(w, dtype=np.float64)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = np.zeros((*w.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def rotation_log(m: np.ndarray) -> np.ndarray:
    """Rotation vectors [..., 3] of rotation matrices [..., 3, 3] (angles below pi)."""
    m = np.asarray(m, dtype=np.float64)
    w = 0.5 * np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                        m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    s = np.linalg.norm(w, axis=-1)
    angle = np.arctan2(s, 0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0))
    scale = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 1.0)
    return w * scale[..., None]


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest to the 3x3 matrix ``m`` in the Frobenius norm (its polar factor)."""
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def validate_pose(c2w, *, name: str = "pose", atol: float = ROTATION_ATOL) -> np.ndarray:
    """Check a 4x4 rigid transform and return it as float64 with its rotation made exactly orthonormal.

    Raises PoseError naming ``name`` and the problem: wrong shape, a non-finite entry, a bottom row
    other than [0, 0, 0, 1], a rotation block that is not orthonormal within ``atol``, or a
    reflection (det -1). Accepts numpy arrays, nested sequences and torch tensors.
    """
    if isinstance(c2w, torch.Tensor):
        c2w = c2w.detach().cpu().numpy()
    try:
        m = np.array(c2w, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseError(f"{name} must be a 4x4 matrix of numbers") from exc
    if m.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise PoseError(f"{name} has a non-finite entry (NaN or Inf)")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise PoseError(f"{name} bottom row must be [0, 0, 0, 1], got {m[3].tolist()}")
    R = m[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > atol:
        raise PoseError(f"{name} rotation is not orthonormal: max |R^T R - I| = {err:.3g} > {atol:g}")
    if np.linalg.det(R) < 0:
        raise PoseError(f"{name} rotation has determinant -1 (a reflection, not a rotation)")
    u, _, vt = np.linalg.svd(R)
    m[:3, :3] = u @ vt  # nearest rotation, so small print rounding never shears the camera
    m[3] = [0.0, 0.0, 0.0, 1.0]
    return m


def world_to_camera(c2w) -> np.ndarray:
    """Inverse of rigid camera-to-world poses: [R^T, -R^T t].

    c2w: array-like  # [..., 4, 4] float64, rigid
    returns np.ndarray  # [..., 4, 4] float64
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape[-2:] != (4, 4):
        raise PoseError(f"c2w must be [..., 4, 4], got shape {c2w.shape}")
    if not np.isfinite(c2w).all():
        raise PoseError("c2w has a non-finite entry (NaN or Inf)")
    rt = np.swapaxes(c2w[..., :3, :3], -1, -2)
    out = np.zeros_like(c2w)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ c2w[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def pose_from_quat(t, q) -> np.ndarray:
    """c2w float64 [4, 4] from a translation (tx, ty, tz) and a quaternion (w, x, y, z)."""
    m = np.eye(4)
    m[:3, :3] = quat_to_rotmat(q)
    m[:3, 3] = np.asarray(t, dtype=np.float64)
    return m


def parse_pose(value, *, name: str = "pose") -> np.ndarray:
    """A camera-to-world pose from its wire forms, validated.

    ``value``: 16 numbers (row-major 4x4 c2w), or 7 numbers (tx, ty, tz, qw, qx, qy, qz), as a
    sequence, an array (a [4, 4] array too) or a string of numbers separated by commas and/or spaces.
    returns np.ndarray  # [4, 4] float64
    """
    if isinstance(value, str):
        parts = [p for p in value.replace(",", " ").split() if p]
        try:
            nums = np.array([float(p) for p in parts], dtype=np.float64)
        except ValueError as exc:
            raise PoseError(f"{name} must be 16 or 7 comma-separated numbers, got {value!r:.200}") from exc
    else:
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        try:
            nums = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise PoseError(f"{name} must be 16 or 7 numbers") from exc
    if nums.size == 16:
        return validate_pose(nums.reshape(4, 4), name=name)
    if nums.size == 7:
        if not np.isfinite(nums).all():
            raise PoseError(f"{name} has a non-finite number (NaN or Inf)")
        if np.linalg.norm(nums[3:]) < 1e-12:
            raise PoseError(f"{name} quaternion (qw, qx, qy, qz) is zero; it describes no rotation")
        return pose_from_quat(nums[:3], nums[3:])
    raise PoseError(f"{name} must have 16 numbers (row-major 4x4 camera-to-world) or 7 "
                    f"(tx, ty, tz, qw, qx, qy, qz), got {nums.size}")


# ---------------------------------------------------------------------------------------- projection

def project(points, w2c, intrinsics: Intrinsics):
    """Pixel coordinates and camera depth of world points; numpy in -> numpy out, torch -> torch.

    points: [N, 3] (numpy or torch; torch keeps its dtype, device and autograd graph)
    w2c: [4, 4] world-to-camera (numpy or torch)
    returns (uv [N, 2], depth [N]). uv is meaningful only where depth > 0; a point at |depth| < 1e-12
    is divided by +-1e-12 instead, so nothing comes out NaN.
    """
    if isinstance(points, torch.Tensor):
        w2c_t = torch.as_tensor(w2c, dtype=points.dtype, device=points.device)
        cam = points @ w2c_t[:3, :3].T + w2c_t[:3, 3]
        z = cam[:, 2]
        z_safe = torch.where(z.abs() < 1e-12, torch.where(z < 0, -1e-12, 1e-12).to(z), z)
        uv = torch.stack([intrinsics.fx * cam[:, 0] / z_safe + intrinsics.cx,
                          intrinsics.fy * cam[:, 1] / z_safe + intrinsics.cy], dim=-1)
        return uv, z
    pts = np.asarray(points)
    dtype = pts.dtype if np.issubdtype(pts.dtype, np.floating) else np.float64
    pts = pts.astype(dtype, copy=False)
    w = np.asarray(w2c, dtype=dtype)
    cam = pts @ w[:3, :3].T + w[:3, 3]
    z = cam[:, 2]
    z_safe = np.where(np.abs(z) < 1e-12, np.where(z < 0, -1e-12, 1e-12), z).astype(dtype)
    uv = np.stack([intrinsics.fx * cam[:, 0] / z_safe + intrinsics.cx,
                   intrinsics.fy * cam[:, 1] / z_safe + intrinsics.cy], axis=-1).astype(dtype)
    return uv, z


# -------------------------------------------------------------------------------------- trajectories

def _slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Shortest-arc spherical interpolation of unit quaternions [M, 4] with weights [M] in [0, 1]."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-8  # nearly identical rotations: the normalised lerp is exact to rounding
    safe = np.where(near, 1.0, sin)
    a = np.where(near, 1.0 - w, np.sin((1.0 - w) * theta) / safe)
    b = np.where(near, w, np.sin(w * theta) / safe)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


class Trajectory:
    """A camera path: poses at increasing int64 µs timestamps, interpolated by slerp + linear.

    t_us: int64 [T] strictly increasing (T >= 1); c2w: float64 [T, 4, 4], each a valid pose.
    """

    def __init__(self, t_us, c2w):
        t = np.asarray(t_us)
        if t.ndim != 1 or t.size == 0:
            raise InvalidInputError(f"t_us must be a non-empty 1-D array, got shape {t.shape}")
        if not np.issubdtype(t.dtype, np.integer):
            raise InvalidInputError(f"t_us must be integer microseconds (int64), got dtype {t.dtype}")
        t = t.astype(np.int64)
        if t.size > 1 and (np.diff(t) <= 0).any():
            raise InvalidInputError("t_us must be strictly increasing")
        poses = np.asarray(c2w, dtype=np.float64)
        if poses.shape != (t.size, 4, 4):
            raise InvalidInputError(f"c2w must be [{t.size}, 4, 4] to match t_us, got shape {poses.shape}")
        poses = np.stack([validate_pose(p, name=f"c2w[{i}]") for i, p in enumerate(poses)])
        self.t_us = t
        self.c2w = poses
        self._quats = rotmat_to_quat(poses[:, :3, :3])
        self._last: tuple[int, np.ndarray] | None = None  # a render asks for its instant's pose twice

    @property
    def start_us(self) -> int:
        return int(self.t_us[0])

    @property
    def end_us(self) -> int:
        return int(self.t_us[-1])

    @property
    def is_static(self) -> bool:
        """True when the camera never moves (one sample, or every pose equal to the first)."""
        return bool(np.abs(self.c2w - self.c2w[:1]).max() <= 1e-12)

    def at(self, t_us) -> np.ndarray:
        """Pose(s) at time(s) t_us (int64 µs), clamped to the span.

        t_us: int or int64 array [M]
        returns float64 [4, 4] for a scalar, [M, 4, 4] for an array.
        """
        scalar = np.ndim(t_us) == 0
        t = np.asarray(t_us)
        if not np.issubdtype(t.dtype, np.integer):
            raise InvalidInputError(f"t_us must be integer microseconds, got dtype {t.dtype}")
        if not scalar:
            return self._at(t)
        last = self._last
        if last is None or last[0] != int(t):
            last = self._last = (int(t), self._at(t)[0])
        return last[1].copy()

    def _at(self, t: np.ndarray) -> np.ndarray:
        """``at`` for integer times, always [M, 4, 4]."""
        # np.minimum / np.maximum: np.clip's dispatch costs more than the work on a few times
        t = np.minimum(np.maximum(t.astype(np.int64).reshape(-1), self.t_us[0]), self.t_us[-1])
        if self.t_us.size == 1:
            return np.repeat(self.c2w[:1], t.size, axis=0)
        i = np.minimum(np.maximum(np.searchsorted(self.t_us, t, side="right") - 1, 0), self.t_us.size - 2)
        t0, t1 = self.t_us[i], self.t_us[i + 1]
        # int64 differences first (exact), float64 only for the ratio: Unix µs do not fit float32.
        w = (t - t0).astype(np.float64) / (t1 - t0).astype(np.float64)
        q = _slerp(self._quats[i], self._quats[i + 1], w)  # unit: no checks needed to make a rotation
        out = np.zeros((t.size, 4, 4))
        out[:, :3, :3] = np.stack(rotmat_entries(*q.T), axis=-1).reshape(-1, 3, 3)
        out[:, :3, 3] = (1.0 - w)[:, None] * self.c2w[i, :3, 3] + w[:, None] * self.c2w[i + 1, :3, 3]
        out[:, 3, 3] = 1.0
        return out

    def __len__(self) -> int:
        return int(self.t_us.size)


# -------------------------------------------------------------------------------------- similarities

@dataclass(frozen=True)
class Similarity:
    """x -> scale * rotation @ x + translation: how one world frame's points sit in another's (e.g. a
    structure-from-motion reconstruction, up to scale, in the true frame)."""

    scale: float
    rotation: np.ndarray
    """float64 [3, 3]."""
    translation: np.ndarray
    """float64 [3]."""

    @classmethod
    def fit(cls, src, dst) -> Similarity:
        """The least-squares similarity taking points ``src`` [N, 3] onto ``dst`` [N, 3] (Umeyama 1991,
        as evo's Sim(3) alignment computes it); ``InvalidInputError`` for fewer than 3 points or points
        that do not span space enough to fix it (all at one place)."""
        src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
        if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
            raise InvalidInputError(f"a similarity needs two [N >= 3, 3] point sets, got {src.shape} and "
                                    f"{dst.shape}")
        if not (np.isfinite(src).all() and np.isfinite(dst).all()):
            raise InvalidInputError("a similarity's points must be finite")
        mu_s, mu_d = src.mean(0), dst.mean(0)
        xs, xd = src - mu_s, dst - mu_d
        var = float((xs**2).sum() / len(src))
        if var <= 1e-18:
            raise InvalidInputError("the source points all sit at one place: no similarity is fixed")
        u, d, vt = np.linalg.svd(xd.T @ xs / len(src))
        sign = np.diag([1.0, 1.0, -1.0 if np.linalg.det(u) * np.linalg.det(vt) < 0 else 1.0])
        rotation = u @ sign @ vt
        scale = float(np.trace(np.diag(d) @ sign) / var)
        return cls(scale, rotation, mu_d - scale * rotation @ mu_s)

    @classmethod
    def fit_poses(cls, src, dst) -> Similarity:
        """The similarity taking cameras ``src`` [N, 4, 4] (c2w) onto ``dst``: its rotation the chordal
        mean of dst_i src_i^T over the cameras' orientations (which fix it even when the centres lie on
        a line, as a walk's do, where ``fit`` leaves the turn about that line free), then its scale and
        translation by least squares on the centres. ``InvalidInputError`` when the centres do not move."""
        src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
        if src.shape != dst.shape or src.ndim != 3 or src.shape[1:] != (4, 4) or len(src) < 2:
            raise InvalidInputError(f"a similarity of poses needs two [N >= 2, 4, 4] sets, got {src.shape} "
                                    f"and {dst.shape}")
        if not (np.isfinite(src).all() and np.isfinite(dst).all()):
            raise InvalidInputError("a similarity's poses must be finite")
        u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3]))
        rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        p, q = src[:, :3, 3], dst[:, :3, 3]
        xs, xd = (p - p.mean(0)) @ rotation.T, q - q.mean(0)
        var = float((xs**2).sum())
        if var <= 1e-18 * max(len(p), 1):
            raise InvalidInputError("the cameras do not move: no scale between the two frames is fixed")
        scale = float((xs * xd).sum() / var)
        if scale <= 0:
            raise InvalidInputError("the two sets of cameras move in opposite directions: no similarity")
        return cls(scale, rotation, q.mean(0) - scale * rotation @ p.mean(0))

    def points(self, xyz) -> np.ndarray:
        """[N, 3] points mapped."""
        return self.scale * np.asarray(xyz, dtype=np.float64) @ self.rotation.T + self.translation

    def poses(self, c2w) -> np.ndarray:
        """[N, 4, 4] camera-to-world poses mapped (their centres moved, their axes turned; no scale in a
        rotation)."""
        out = np.array(c2w, dtype=np.float64, copy=True).reshape(-1, 4, 4)
        out[:, :3, :3] = self.rotation @ out[:, :3, :3]
        out[:, :3, 3] = self.points(out[:, :3, 3])
        return out

    def inverse(self) -> Similarity:
        return Similarity(1.0 / self.scale, self.rotation.T, -self.rotation.T @ self.translation / self.scale)


__all__ = ["Intrinsics", "Similarity", "Trajectory", "parse_pose", "pose_from_quat", "project",
           "quat_multiply", "quat_normalize", "quat_to_rotmat", "rotmat_to_quat", "validate_pose",
           "world_to_camera"]
