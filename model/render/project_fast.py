"""Per-Gaussian preprocessing on the CPU (numba) with analytic backwards: the EWA projection of
``projection.ewa_project`` and the SH colour of ``sh.sh_to_color``, as autograd Functions.

The same math as the torch versions (Jacobian with the frustum-clamped x/z, y/z, depth clamped at
``near``, the 0.3 px^2 low-pass, det as a sum of squared minors, colour = SH + 0.5 clamped at 0),
evaluated per Gaussian in float64; the torch versions stay the reference (the tests compare values
and gradients). The projection's kernels read and write columns ([3, N], not [N, 3]) and branch only
on forward/backward, which each kernel fixes, so LLVM vectorises them (3x faster than the row-wise
scalar loop, forward and backward: ``bench.render --profile numba``); they run parallel over Gaussians
on torch's thread count. A Gaussian whose outputs get no gradient (one the rasterizer culled) gets
exactly zero, never 0 * inf.

Backward of the projection, with M = J R_w2c R(q) diag(s) [2, 3], cov = M M^T + 0.3 I and
conic = (c, -b, a) / det:
    d det = -(g_A c - g_B b + g_C a) / det^2,  d a = g_C / det + 0.3 d det,  d c = g_A / det + 0.3 d det
    d M_0 = 2 d a M_0 + d b M_1 + d det d(minors^2)/d M_0  (M_1 alike)
then through diag(s), R(q) (with q normalised), J (inv_z, the clamped x/z, y/z) and the camera
transform, as in gsplat's projection backward.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from edmcgs.geometry import Intrinsics
from edmcgs.model.render.jit import in_torch_threads, njit_cached
from edmcgs.model.render.projection import FRUSTUM_SLACK, LOWPASS
from edmcgs.model.render.sh import SH_C0, SH_C1, SH_C2, SH_C3

__all__ = ["project_fast", "sh_color_fast"]


@njit_cached(parallel=True, nogil=True, error_model="numpy")
def _project_forward(mt, qt, st, w2c, cam, lims, near, out):
    """out[:, i] = (mean2d x, y, cov2d a, b, c, conic a, b, c, depth) of Gaussian i."""
    g = np.zeros((1, 1), out.dtype)  # no incoming gradients (not read)
    for i in numba.prange(mt.shape[1]):
        _project_one(i, mt, qt, st, w2c, cam, lims, near, g, g, g, out, g, g, g, False)


@njit_cached(parallel=True, nogil=True, error_model="numpy")
def _project_backward(mt, qt, st, w2c, cam, lims, near, g_mean2d, g_conic, g_depth, d_means, d_quats,
                      d_scales):
    """d_means, d_quats, d_scales [:, i] from the incoming gradients [:, i] of mean2d, conic, depth."""
    out = np.zeros((1, 1), d_means.dtype)  # no forward outputs (not written)
    for i in numba.prange(mt.shape[1]):
        _project_one(i, mt, qt, st, w2c, cam, lims, near, g_mean2d, g_conic, g_depth, out, d_means, d_quats,
                     d_scales, True)


@njit_cached(error_model="numpy", inline="always")
def _project_one(i, mt, qt, st, w2c, cam, lims, near, g_mean2d, g_conic, g_depth, out, d_means, d_quats,
                 d_scales, backward):
    """Gaussian i, every array in columns [k, i]. Branch-free apart from ``backward``, a constant of
    each caller once inlined, so that LLVM vectorises both loops."""
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    lim_xn, lim_xp, lim_yn, lim_yp = lims[0], lims[1], lims[2], lims[3]
    px, py, pz = np.float64(mt[0, i]), np.float64(mt[1, i]), np.float64(mt[2, i])
    x = w2c[0, 0] * px + w2c[0, 1] * py + w2c[0, 2] * pz + w2c[0, 3]
    y = w2c[1, 0] * px + w2c[1, 1] * py + w2c[1, 2] * pz + w2c[1, 3]
    z = w2c[2, 0] * px + w2c[2, 1] * py + w2c[2, 2] * pz + w2c[2, 3]
    inv_z = 1.0 / max(z, near)
    xr, yr = x * inv_z, y * inv_z
    xz = min(max(xr, -lim_xn), lim_xp)
    yz = min(max(yr, -lim_yn), lim_yp)
    j00, j02 = fx * inv_z, -fx * xz * inv_z
    j11, j12 = fy * inv_z, -fy * yz * inv_z
    # P = J R_w2c [2, 3]; G = R(q) [3, 3]; PG = P G; M = PG diag(s)
    p00, p01, p02 = (j00 * w2c[0, 0] + j02 * w2c[2, 0], j00 * w2c[0, 1] + j02 * w2c[2, 1],
                     j00 * w2c[0, 2] + j02 * w2c[2, 2])
    p10, p11, p12 = (j11 * w2c[1, 0] + j12 * w2c[2, 0], j11 * w2c[1, 1] + j12 * w2c[2, 1],
                     j11 * w2c[1, 2] + j12 * w2c[2, 2])
    q0, q1, q2, q3 = np.float64(qt[0, i]), np.float64(qt[1, i]), np.float64(qt[2, i]), np.float64(qt[3, i])
    qn = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    qw, qx, qy, qz = q0 / qn, q1 / qn, q2 / qn, q3 / qn
    g00, g01, g02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
    g10, g11, g12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
    g20, g21, g22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
    pg00, pg01, pg02 = (p00 * g00 + p01 * g10 + p02 * g20, p00 * g01 + p01 * g11 + p02 * g21,
                        p00 * g02 + p01 * g12 + p02 * g22)
    pg10, pg11, pg12 = (p10 * g00 + p11 * g10 + p12 * g20, p10 * g01 + p11 * g11 + p12 * g21,
                        p10 * g02 + p11 * g12 + p12 * g22)
    s0, s1, s2 = np.float64(st[0, i]), np.float64(st[1, i]), np.float64(st[2, i])
    m00, m01, m02 = pg00 * s0, pg01 * s1, pg02 * s2
    m10, m11, m12 = pg10 * s0, pg11 * s1, pg12 * s2
    a0 = m00 * m00 + m01 * m01 + m02 * m02
    b = m00 * m10 + m01 * m11 + m02 * m12
    c0 = m10 * m10 + m11 * m11 + m12 * m12
    k01, k02, k12 = m00 * m11 - m01 * m10, m00 * m12 - m02 * m10, m01 * m12 - m02 * m11
    det = k01 * k01 + k02 * k02 + k12 * k12 + LOWPASS * (a0 + c0) + LOWPASS * LOWPASS
    a, c = a0 + LOWPASS, c0 + LOWPASS
    if not backward:
        out[0, i] = fx * x * inv_z + cx
        out[1, i] = fy * y * inv_z + cy
        out[2, i], out[3, i], out[4, i] = a, b, c
        out[5, i], out[6, i], out[7, i] = c / det, -b / det, a / det
        out[8, i] = z
        return
    gu, gv = np.float64(g_mean2d[0, i]), np.float64(g_mean2d[1, i])
    ga, gb, gc = np.float64(g_conic[0, i]), np.float64(g_conic[1, i]), np.float64(g_conic[2, i])
    gz = np.float64(g_depth[0, i])
    # A Gaussian with no incoming gradient (one the rasterizer culled) gets exactly zero, never 0 * inf:
    # everything is computed and then replaced (a select, not a branch).
    live = (gu != 0) | (gv != 0) | (ga != 0) | (gb != 0) | (gc != 0) | (gz != 0)
    # conic -> (a, b, c, det) -> M
    inv_det = 1.0 / det
    g_det = -(ga * c - gb * b + gc * a) * inv_det * inv_det
    g_a = 2 * (gc * inv_det + LOWPASS * g_det)
    g_c = 2 * (ga * inv_det + LOWPASS * g_det)
    g_b = -gb * inv_det
    t01, t02, t12 = 2 * g_det * k01, 2 * g_det * k02, 2 * g_det * k12
    dm00 = g_a * m00 + g_b * m10 + t01 * m11 + t02 * m12
    dm01 = g_a * m01 + g_b * m11 - t01 * m10 + t12 * m12
    dm02 = g_a * m02 + g_b * m12 - t02 * m10 - t12 * m11
    dm10 = g_c * m10 + g_b * m00 - t01 * m01 - t02 * m02
    dm11 = g_c * m11 + g_b * m01 + t01 * m00 - t12 * m02
    dm12 = g_c * m12 + g_b * m02 + t02 * m00 + t12 * m01
    # M = PG diag(s): scales, then G (rotation) and P
    d_scales[0, i] = dm00 * pg00 + dm10 * pg10 if live else 0.0
    d_scales[1, i] = dm01 * pg01 + dm11 * pg11 if live else 0.0
    d_scales[2, i] = dm02 * pg02 + dm12 * pg12 if live else 0.0
    e00, e01, e02, e10, e11, e12 = dm00 * s0, dm01 * s1, dm02 * s2, dm10 * s0, dm11 * s1, dm12 * s2  # d PG
    r00, r01, r02 = p00 * e00 + p10 * e10, p00 * e01 + p10 * e11, p00 * e02 + p10 * e12  # d G
    r10, r11, r12 = p01 * e00 + p11 * e10, p01 * e01 + p11 * e11, p01 * e02 + p11 * e12
    r20, r21, r22 = p02 * e00 + p12 * e10, p02 * e01 + p12 * e11, p02 * e02 + p12 * e12
    dp00, dp01, dp02 = (e00 * g00 + e01 * g01 + e02 * g02, e00 * g10 + e01 * g11 + e02 * g12,
                        e00 * g20 + e01 * g21 + e02 * g22)
    dp10, dp11, dp12 = (e10 * g00 + e11 * g01 + e12 * g02, e10 * g10 + e11 * g11 + e12 * g12,
                        e10 * g20 + e11 * g21 + e12 * g22)
    dw = 2 * (-qz * r01 + qy * r02 + qz * r10 - qx * r12 - qy * r20 + qx * r21)
    dx = 2 * (qy * r01 + qz * r02 + qy * r10 - 2 * qx * r11 - qw * r12 + qz * r20 + qw * r21 - 2 * qx * r22)
    dy = 2 * (-2 * qy * r00 + qx * r01 + qw * r02 + qx * r10 + qz * r12 - qw * r20 + qz * r21 - 2 * qy * r22)
    dz = 2 * (-2 * qz * r00 - qw * r01 + qx * r02 + qw * r10 - 2 * qz * r11 + qy * r12 + qx * r20 + qy * r21)
    dot = qw * dw + qx * dx + qy * dy + qz * dz
    d_quats[0, i] = (dw - qw * dot) / qn if live else 0.0
    d_quats[1, i] = (dx - qx * dot) / qn if live else 0.0
    d_quats[2, i] = (dy - qy * dot) / qn if live else 0.0
    d_quats[3, i] = (dz - qz * dot) / qn if live else 0.0
    # P = J R_w2c -> J entries -> inv_z, x/z, y/z (the clamps pass no gradient where they bite)
    dj00 = dp00 * w2c[0, 0] + dp01 * w2c[0, 1] + dp02 * w2c[0, 2]
    dj02 = dp00 * w2c[2, 0] + dp01 * w2c[2, 1] + dp02 * w2c[2, 2]
    dj11 = dp10 * w2c[1, 0] + dp11 * w2c[1, 1] + dp12 * w2c[1, 2]
    dj12 = dp10 * w2c[2, 0] + dp11 * w2c[2, 1] + dp12 * w2c[2, 2]
    d_xz = -fx * inv_z * dj02 if (-lim_xn <= xr) & (xr <= lim_xp) else 0.0
    d_yz = -fy * inv_z * dj12 if (-lim_yn <= yr) & (yr <= lim_yp) else 0.0
    d_x = (d_xz + gu * fx) * inv_z
    d_y = (d_yz + gv * fy) * inv_z
    d_inv = (fx * dj00 - fx * xz * dj02 + fy * dj11 - fy * yz * dj12 + d_xz * x + d_yz * y
             + gu * fx * x + gv * fy * y)
    d_z = gz - (d_inv * inv_z * inv_z if z >= near else 0.0)
    for k in range(3):
        d_means[k, i] = w2c[0, k] * d_x + w2c[1, k] * d_y + w2c[2, k] * d_z if live else 0.0


def _limits(intrinsics: Intrinsics) -> np.ndarray:
    """The frustum limits of x/z and y/z (``ewa_project``'s clamp)."""
    k = intrinsics
    slack_x = FRUSTUM_SLACK * 0.5 * k.width / k.fx
    slack_y = FRUSTUM_SLACK * 0.5 * k.height / k.fy
    return np.array([k.cx / k.fx + slack_x, (k.width - k.cx) / k.fx + slack_x,
                     k.cy / k.fy + slack_y, (k.height - k.cy) / k.fy + slack_y])


def _columns(*tensors: Tensor, dtype: torch.dtype) -> list[np.ndarray]:
    """Each [N, K] tensor as a C-contiguous [K, N] numpy array of ``dtype`` (the kernels' columns)."""
    return [t.detach().to(dtype).reshape(t.shape[0], math.prod(t.shape[1:])).T.contiguous().numpy()
            for t in tensors]


class ProjectFast(torch.autograd.Function):
    """(means, quats, scales) -> (mean2d [N, 2], cov2d [N, 3] (not differentiable), conic [N, 3],
    depth [N]); w2c [4, 4] float64 numpy, intrinsics and near are constants."""

    @staticmethod
    def forward(ctx, means, quats, scales, w2c, intrinsics, near):
        dtype = means.dtype
        cols = _columns(means, quats, scales, dtype=dtype)
        out = np.empty((9, means.shape[0]), cols[0].dtype)
        k = intrinsics
        cam = np.array([k.fx, k.fy, k.cx, k.cy], np.float64)
        ctx.constants = (w2c, cam, _limits(intrinsics), float(near))
        in_torch_threads(_project_forward, *cols, *ctx.constants, out)
        ctx.cols, ctx.dtype = cols, dtype  # copies: the backward sees the inputs as they were here
        mean2d, cov2d, conic, depth = (torch.from_numpy(np.ascontiguousarray(out[rows].T))
                                       for rows in (slice(0, 2), slice(2, 5), slice(5, 8), 8))
        ctx.mark_non_differentiable(cov2d)
        return mean2d, cov2d, conic, depth

    @staticmethod
    def backward(ctx, g_mean2d, g_cov2d, g_conic, g_depth):
        grads = [np.empty_like(c) for c in ctx.cols]
        in_torch_threads(_project_backward, *ctx.cols, *ctx.constants,
                         *_columns(g_mean2d, g_conic, g_depth, dtype=ctx.dtype), *grads)
        return (*(torch.from_numpy(g.T.copy()) for g in grads), None, None, None)


def project_fast(means: Tensor, quats: Tensor, scales: Tensor, w2c: np.ndarray, intrinsics: Intrinsics,
                 near: float):
    """``ewa_project`` on the CPU: (mean2d, cov2d, conic, depth), differentiable w.r.t. means,
    quats and scales (cov2d is for culling only). w2c: [4, 4], converted to float64."""
    w2c = np.ascontiguousarray(np.asarray(w2c, np.float64))
    return ProjectFast.apply(means, quats, scales, w2c, intrinsics, near)


@njit_cached(nogil=True)
def _sh(coeffs, means, centre, g_color, color, d_coeffs, d_means, backward):
    """Forward: color = max(SH(coeffs, dir) + 0.5, 0) with dir the unit vector from the camera
    centre to the mean. Backward: d_coeffs and d_means from g_color."""
    basis, grad = np.empty(16), np.empty((16, 3))  # the basis and its gradient, reused per Gaussian
    for i in range(coeffs.shape[0]):
        _sh_one(i, coeffs, means, centre, g_color, color, d_coeffs, d_means, backward, basis, grad)


@njit_cached(error_model="numpy", inline="always")
def _sh_one(i, coeffs, means, centre, g_color, color, d_coeffs, d_means, backward, basis, grad):
    ncoef, nch = coeffs.shape[1], coeffs.shape[2]
    vx = np.float64(means[i, 0]) - centre[0]
    vy = np.float64(means[i, 1]) - centre[1]
    vz = np.float64(means[i, 2]) - centre[2]
    norm = max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-12)
    x, y, z = vx / norm, vy / norm, vz / norm
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    basis[:] = 0.0
    grad[:] = 0.0  # d basis / d (x, y, z)
    basis[0] = SH_C0
    if ncoef > 1:
        basis[1], basis[2], basis[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
        grad[1, 1], grad[2, 2], grad[3, 0] = -SH_C1, SH_C1, -SH_C1
    if ncoef > 4:
        basis[4] = SH_C2[0] * xy
        basis[5] = SH_C2[1] * yz
        basis[6] = SH_C2[2] * (2 * zz - xx - yy)
        basis[7] = SH_C2[3] * xz
        basis[8] = SH_C2[4] * (xx - yy)
        grad[4, 0], grad[4, 1] = SH_C2[0] * y, SH_C2[0] * x
        grad[5, 1], grad[5, 2] = SH_C2[1] * z, SH_C2[1] * y
        grad[6, 0], grad[6, 1], grad[6, 2] = -2 * SH_C2[2] * x, -2 * SH_C2[2] * y, 4 * SH_C2[2] * z
        grad[7, 0], grad[7, 2] = SH_C2[3] * z, SH_C2[3] * x
        grad[8, 0], grad[8, 1] = 2 * SH_C2[4] * x, -2 * SH_C2[4] * y
    if ncoef > 9:
        basis[9] = SH_C3[0] * y * (3 * xx - yy)
        basis[10] = SH_C3[1] * xy * z
        basis[11] = SH_C3[2] * y * (4 * zz - xx - yy)
        basis[12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        basis[13] = SH_C3[4] * x * (4 * zz - xx - yy)
        basis[14] = SH_C3[5] * z * (xx - yy)
        basis[15] = SH_C3[6] * x * (xx - 3 * yy)
        grad[9, 0], grad[9, 1] = 6 * SH_C3[0] * xy, SH_C3[0] * (3 * xx - 3 * yy)
        grad[10, 0], grad[10, 1], grad[10, 2] = SH_C3[1] * yz, SH_C3[1] * xz, SH_C3[1] * xy
        grad[11, 0], grad[11, 1] = -2 * SH_C3[2] * xy, SH_C3[2] * (4 * zz - xx - 3 * yy)
        grad[11, 2] = 8 * SH_C3[2] * yz
        grad[12, 0], grad[12, 1] = -6 * SH_C3[3] * xz, -6 * SH_C3[3] * yz
        grad[12, 2] = SH_C3[3] * (6 * zz - 3 * xx - 3 * yy)
        grad[13, 0], grad[13, 1] = SH_C3[4] * (4 * zz - 3 * xx - yy), -2 * SH_C3[4] * xy
        grad[13, 2] = 8 * SH_C3[4] * xz
        grad[14, 0], grad[14, 1] = 2 * SH_C3[5] * xz, -2 * SH_C3[5] * yz
        grad[14, 2] = SH_C3[5] * (xx - yy)
        grad[15, 0], grad[15, 1] = SH_C3[6] * (3 * xx - 3 * yy), -6 * SH_C3[6] * xy
    gx = gy = gz = 0.0
    for ch in range(nch):
        value = 0.5
        for k in range(ncoef):
            value += basis[k] * np.float64(coeffs[i, k, ch])
        if not backward:
            color[i, ch] = max(value, 0.0)
            continue
        g = np.float64(g_color[i, ch]) if value >= 0 else 0.0  # clamp_min passes at the edge
        for k in range(ncoef):
            d_coeffs[i, k, ch] = basis[k] * g
            gck = np.float64(coeffs[i, k, ch]) * g
            gx += grad[k, 0] * gck
            gy += grad[k, 1] * gck
            gz += grad[k, 2] * gck
    if backward:  # through dir = v / max(|v|, eps)
        if norm > 1e-12:
            dot = x * gx + y * gy + z * gz
            gx, gy, gz = (gx - x * dot) / norm, (gy - y * dot) / norm, (gz - z * dot) / norm
        else:
            gx, gy, gz = gx / norm, gy / norm, gz / norm
        d_means[i, 0], d_means[i, 1], d_means[i, 2] = gx, gy, gz


class ShColorFast(torch.autograd.Function):
    """(coeffs [N, K, C], means [N, 3]) -> colour [N, C]; centre [3] float64 numpy is a constant."""

    @staticmethod
    def forward(ctx, coeffs, means, centre):
        c, m = coeffs.detach().contiguous().numpy(), means.detach().contiguous().numpy()
        color = np.empty((c.shape[0], c.shape[2]), c.dtype)
        empty = np.zeros((0, 3), c.dtype)
        _sh(c, m, centre, empty, color, np.zeros((0, 1, 1), c.dtype), empty, False)
        ctx.save_for_backward(coeffs, means)
        ctx.centre = centre
        return torch.from_numpy(color)

    @staticmethod
    def backward(ctx, g_color):
        coeffs, means = ctx.saved_tensors
        c, m = coeffs.detach().contiguous().numpy(), means.detach().contiguous().numpy()
        d_coeffs, d_means = np.empty_like(c), np.empty_like(m)
        _sh(c, m, ctx.centre, g_color.to(coeffs.dtype).contiguous().numpy(), np.zeros((0, 1), c.dtype),
            d_coeffs, d_means, True)
        return torch.from_numpy(d_coeffs), torch.from_numpy(d_means), None


def sh_color_fast(coeffs: Tensor, means: Tensor, w2c: np.ndarray) -> Tensor:
    """``sh_to_color`` towards each Gaussian from the camera centre of w2c, on the CPU;
    differentiable w.r.t. coeffs [N, K, C] and means [N, 3]."""
    if coeffs.shape[1] == 1:  # degree 0 sees no direction: two torch ops, 8x faster than the kernel
        return (coeffs[:, 0] * SH_C0 + 0.5).clamp_min(0.0)
    w2c = np.asarray(w2c, np.float64)
    centre = np.ascontiguousarray(-(w2c[:3, :3].T @ w2c[:3, 3]))
    return ShColorFast.apply(coeffs, means, centre)


KERNELS = (_project_forward, _project_backward)
"""The projection's kernels a training step compiles on first use (``jit.compiled``)."""
