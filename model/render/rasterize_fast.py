"""Fast CPU inference rasterizer (numba): the same math as ``rasterize``, numpy in and out.

Three stages: per-Gaussian preprocessing (EWA projection and screen rectangle, the math of
``projection``, in float64, parallel over Gaussians and branch-free so that it vectorises; SH colour
apart, by the training path's ``project_fast._sh_one``), binning into 16x16 tiles in depth order, and
per-tile front-to-back blending, parallel over tiles. Blending visits each splat's ``screen_rect``
(the pixels where its alpha can reach ``alpha_min``; this changes no pixel value) in runs of 8 or 16
pixels with a branch-free float32 body and ``simd_exp``'s 2^x (the conics come scaled by log2(e) and
the opacity as log2 opacity in the exponent: no range reduction by ln 2 and no multiply per pixel),
which LLVM turns into AVX2 code; a pixel that has stopped is marked by a negative transmittance.

JIT cache: kernels are compiled with ``cache=True`` where numba finds a writable place (``jit``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import Intrinsics
from edmcgs.model.render.io import RenderOutput, as_float32_arrays, check_inputs
from edmcgs.model.render.jit import njit_cached as _jit
from edmcgs.model.render.project_fast import _sh_one
from edmcgs.model.render.projection import ALPHA_MAX, ALPHA_MIN, FRUSTUM_SLACK, LOWPASS, SIGMAS, T_MIN, TILE
from edmcgs.model.render.simd_exp import LOG2E, exp2_nonpositive
from edmcgs.model.render.tiles import all_stopped, bin_tiles, depth_order

__all__ = ["RenderOutput", "rasterize_fast"]


@_jit(parallel=True, nogil=True, error_model="numpy")
def _project(mt, qt, st, opac, log_o, w2c, fx, fy, cx, cy, width, height, near, alpha_min, splat, rect):
    """Per Gaussian i, in float64, in columns: splat[:, i] = (mean x, mean y, -A/2, -B, -C/2, log2
    opacity, camera z) with (A, B, C) the conic scaled by log2(e) (alpha = 2^(exponent + log2
    opacity)); rect[:, i] = its pixel rectangle (x0, y0, x1, y1), empty (all 0) when culled.

    Branch-free and column-wise, so that LLVM vectorises it (3x faster than a scalar loop that skips
    the culled ones early and writes rows): every Gaussian is projected, and one mask at the end culls
    what lies behind the near plane, is fainter than alpha_min, projects to non-finite numbers or
    covers no pixel; the culled ones' splat is not read. mt, qt, st: means, quats and scales as rows
    [3 or 4, N]; log_o: float64 log of the opacities."""
    n = mt.shape[1]
    r00, r01, r02 = w2c[0, 0], w2c[0, 1], w2c[0, 2]
    r10, r11, r12 = w2c[1, 0], w2c[1, 1], w2c[1, 2]
    r20, r21, r22 = w2c[2, 0], w2c[2, 1], w2c[2, 2]
    t0, t1, t2 = w2c[0, 3], w2c[1, 3], w2c[2, 3]
    slack_x = FRUSTUM_SLACK * 0.5 * width / fx
    slack_y = FRUSTUM_SLACK * 0.5 * height / fy
    lim_xn, lim_xp = cx / fx + slack_x, (width - cx) / fx + slack_x
    lim_yn, lim_yp = cy / fy + slack_y, (height - cy) / fy + slack_y
    w, h = float(width), float(height)
    grid_x = float((width + TILE - 1) // TILE)
    grid_y = float((height + TILE - 1) // TILE)
    has_min = alpha_min > 0
    log_alpha_min = math.log(alpha_min) if has_min else 0.0
    for i in numba.prange(n):
        px, py, pz = np.float64(mt[0, i]), np.float64(mt[1, i]), np.float64(mt[2, i])
        x = r00 * px + r01 * py + r02 * pz + t0
        y = r10 * px + r11 * py + r12 * pz + t1
        z = r20 * px + r21 * py + r22 * pz + t2
        inv_z = 1.0 / z
        u = fx * x * inv_z + cx
        v = fy * y * inv_z + cy
        xz = min(max(x * inv_z, -lim_xn), lim_xp)
        yz = min(max(y * inv_z, -lim_yn), lim_yp)
        j00, j02 = fx * inv_z, -fx * xz * inv_z
        j11, j12 = fy * inv_z, -fy * yz * inv_z
        # rows of J @ R_w2c
        a0x, a0y, a0z = j00 * r00 + j02 * r20, j00 * r01 + j02 * r21, j00 * r02 + j02 * r22
        a1x, a1y, a1z = j11 * r10 + j12 * r20, j11 * r11 + j12 * r21, j11 * r12 + j12 * r22
        qw, qx = np.float64(qt[0, i]), np.float64(qt[1, i])
        qy, qz = np.float64(qt[2, i]), np.float64(qt[3, i])
        qn = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
        g00, g01, g02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        g10, g11, g12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        g20, g21, g22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        s0, s1, s2 = np.float64(st[0, i]), np.float64(st[1, i]), np.float64(st[2, i])
        # M = (J R_w2c) R_g diag(s); cov2d = M M^T
        m00 = (a0x * g00 + a0y * g10 + a0z * g20) * s0
        m01 = (a0x * g01 + a0y * g11 + a0z * g21) * s1
        m02 = (a0x * g02 + a0y * g12 + a0z * g22) * s2
        m10 = (a1x * g00 + a1y * g10 + a1z * g20) * s0
        m11 = (a1x * g01 + a1y * g11 + a1z * g21) * s1
        m12 = (a1x * g02 + a1y * g12 + a1z * g22) * s2
        ca0 = m00 * m00 + m01 * m01 + m02 * m02
        cb = m00 * m10 + m01 * m11 + m02 * m12
        cc0 = m10 * m10 + m11 * m11 + m12 * m12
        k01, k02, k12 = m00 * m11 - m01 * m10, m00 * m12 - m02 * m10, m01 * m12 - m02 * m11
        det = k01 * k01 + k02 * k02 + k12 * k12 + LOWPASS * (ca0 + cc0) + LOWPASS * LOWPASS
        ca, cc = ca0 + LOWPASS, cc0 + LOWPASS
        con_a, con_b, con_c = cc / det, -cb / det, ca / det
        # x - x is 0 exactly when x is finite (a comparison, not a call: it vectorises)
        finite = (((det - det) == 0) & ((ca - ca) == 0) & ((cc - cc) == 0) & ((con_a - con_a) == 0)
                  & ((con_b - con_b) == 0) & ((con_c - con_c) == 0) & ((u - u) == 0) & ((v - v) == 0))
        lam = 0.5 * (ca + cc) + math.sqrt(max(0.1, 0.25 * (ca - cc) ** 2 + cb * cb))
        radius = np.ceil(SIGMAS * math.sqrt(lam))
        tx0 = min(max(np.floor((u - radius) / TILE), 0.0), grid_x)
        tx1 = min(max(np.floor((u + radius) / TILE) + 1.0, 0.0), grid_x)
        ty0 = min(max(np.floor((v - radius) / TILE), 0.0), grid_y)
        ty1 = min(max(np.floor((v + radius) / TILE) + 1.0, 0.0), grid_y)
        # the ellipse (pixel - mean)^T conic (pixel - mean) <= tau holds every pixel whose alpha can
        # reach alpha_min; 0.1% + 1e-3 of slack in tau covers float32 rounding in the blending
        lo = log_o[i]
        tau = max(2.0 * (lo - log_alpha_min) * 1.001 + 1e-3, 0.0) if has_min else math.inf
        ex, ey = math.sqrt(tau * ca), math.sqrt(tau * cc)
        x0 = min(max(max(tx0 * TILE, np.ceil(u - ex)), 0.0), w)
        x1 = min(max(min(min(tx1 * TILE, w), np.floor(u + ex) + 1), 0.0), w)
        y0 = min(max(max(ty0 * TILE, np.ceil(v - ey)), 0.0), h)
        y1 = min(max(min(min(ty1 * TILE, h), np.floor(v + ey) + 1), 0.0), h)
        keep = (z > near) & (opac[i] >= alpha_min) & finite & (x0 < x1) & (y0 < y1)
        rect[0, i] = np.int32(x0) if keep else 0
        rect[1, i] = np.int32(y0) if keep else 0
        rect[2, i] = np.int32(x1) if keep else 0
        rect[3, i] = np.int32(y1) if keep else 0
        splat[0, i], splat[1, i] = u, v
        splat[2, i], splat[3, i], splat[4, i] = -0.5 * LOG2E * con_a, -LOG2E * con_b, -0.5 * LOG2E * con_c
        splat[5, i] = LOG2E * lo
        splat[6, i] = z


@_jit(parallel=True, nogil=True)
def _sh_colors(coeffs, means, centre, rect, color):
    """color[i] = the SH colour of Gaussian i seen from ``centre`` (the training path's ``_sh_one``), for
    those not culled; in blocks, each with its own scratch."""
    n = means.shape[0]
    empty2, empty3 = np.zeros((0, 3), color.dtype), np.zeros((0, 1, 1), color.dtype)
    for block in numba.prange((n + _SH_BLOCK - 1) // _SH_BLOCK):
        basis, grad = np.empty(16), np.empty((16, 3))
        for i in range(block * _SH_BLOCK, min(n, (block + 1) * _SH_BLOCK)):
            if rect[i, 2] > rect[i, 0]:
                _sh_one(i, coeffs, means, centre, empty2, color, empty3, empty2, False, basis, grad)


_SH_BLOCK = 256
"""Gaussians per work item of ``_sh_colors``."""


_STATE = 5 * TILE * TILE
"""Per-tile state: transmittance (negative once the pixel stopped), 3 colour sums, depth sum."""
_PLANE = np.uint64(TILE * TILE)
"""One row of that state, as an unsigned index."""


@_jit(fastmath={"contract"}, inline="always")
def _blend_run(st, p0, dx0, ca, rowb, rowc, c0, c1, c2, z, alpha_min, t_min, want_depth, lanes):
    """Blend one splat into the ``lanes`` pixels st[p0:p0 + lanes] of a tile row (8 or 16, a constant
    at each call); dx0 = x - mean x of the first; rowc holds log2 opacity. Branch-free so that LLVM
    vectorises it; the indices are unsigned to spare it the negative-index wraparound that would
    otherwise block vectorisation."""
    for j in range(lanes):
        p = p0 + np.uint64(j)
        dx = dx0 + np.float32(j)
        alpha = min(exp2_nonpositive(dx * (ca * dx + rowb) + rowc), np.float32(ALPHA_MAX))
        t = st[p]
        w = alpha * t
        t_next = t - w
        live = (alpha >= alpha_min) & (t > np.float32(0.0))
        take = live & (t_next >= t_min)
        w = w if take else np.float32(0.0)
        st[_PLANE + p] += w * c0
        st[np.uint64(2) * _PLANE + p] += w * c1
        st[np.uint64(3) * _PLANE + p] += w * c2
        if want_depth:  # a constant in each copy of ``_blend_tile``
            st[np.uint64(4) * _PLANE + p] += w * z
        st[p] = t_next if take else (-t if live else t)


@_jit(fastmath={"contract"}, inline="always")
def _blend_tile(st, first_k, last_k, ids, splat, depth, rect, color, ox, oy, tw, th, alpha_min, t_min,
                want_depth):
    """Blend the splats ids[first_k:last_k] (front to back) into the tile at (ox, oy), ``tw`` x ``th``
    pixels, until every pixel has stopped."""
    nch = color.shape[1]
    for k in range(first_k, last_k):
        g = ids[k]
        x0 = max(rect[g, 0] - ox, 0)
        x1 = min(rect[g, 2] - ox, tw)
        y0 = max(rect[g, 1] - oy, 0)
        y1 = min(rect[g, 3] - oy, th)
        mx = np.float32(splat[g, 0] - ox)
        my = np.float32(splat[g, 1] - oy)
        ca, cb, cc = np.float32(splat[g, 2]), np.float32(splat[g, 3]), np.float32(splat[g, 4])
        lo, z = np.float32(splat[g, 5]), np.float32(depth[g])
        c0 = color[g, 0]
        c1 = color[g, 1] if nch == 3 else np.float32(0.0)
        c2 = color[g, 2] if nch == 3 else np.float32(0.0)
        # one run per row covering [x0, x1): 8 pixels anywhere in the tile row when the span
        # fits in them, else the whole row (pixels outside the span are skipped anyway)
        if x1 - x0 <= 8:
            first = min(x0, TILE - 8)
            for ly in range(y0, y1):
                dy = np.float32(ly) - my
                _blend_run(st, np.uint64(ly * TILE + first), np.float32(first) - mx, ca, cb * dy,
                           cc * dy * dy + lo, c0, c1, c2, z, alpha_min, t_min, want_depth, 8)
        else:
            for ly in range(y0, y1):
                dy = np.float32(ly) - my
                _blend_run(st, np.uint64(ly * TILE), -mx, ca, cb * dy, cc * dy * dy + lo, c0, c1, c2, z,
                           alpha_min, t_min, want_depth, TILE)
        if (k - first_k) % 16 == 15:  # every 16 splats: has every pixel stopped?
            if all_stopped(st):
                break


@_jit(parallel=True, nogil=True, fastmath={"contract"})
def _blend(start, ids, splat, depth, rect, color, background, width, height, grid_x, alpha_min, t_min,
           want_depth, image, alpha_out, depth_out):
    """Front-to-back blending of every tile's list; writes image, alpha and (want_depth) expected depth,
    flat views of [H, W, C], [H, W] and [H, W]."""
    nch = color.shape[1]
    bg0 = background[0]
    bg1 = background[1] if nch == 3 else np.float32(0.0)
    bg2 = background[2] if nch == 3 else np.float32(0.0)
    n_tiles = grid_x * ((height + TILE - 1) // TILE)
    # One tile per work item, handed to threads one at a time (the caller sets a chunk size of 1),
    # in raster order: busy regions are shared, a preempted thread holds up one tile only, and a
    # thread's next tile is usually beside its last, whose splats it still has in cache. (Tiles dealt
    # round-robin to 128 items were 6% slower on one thread and 15% on two.)
    for t in numba.prange(n_tiles):
        st = np.empty(_STATE, np.float32)
        ox = (t % grid_x) * TILE
        oy = (t // grid_x) * TILE
        tw = min(TILE, width - ox)
        th = min(TILE, height - oy)
        for ly in range(TILE):  # pixels outside the image start stopped
            for lx in range(TILE):
                st[ly * TILE + lx] = 1.0 if (lx < tw and ly < th) else -1.0
        st[TILE * TILE:] = 0.0
        # want_depth as a constant in each copy: the other loses its depth sums altogether
        if want_depth:
            _blend_tile(st, start[t], start[t + 1], ids, splat, depth, rect, color, ox, oy, tw, th,
                        alpha_min, t_min, True)
        else:
            _blend_tile(st, start[t], start[t + 1], ids, splat, depth, rect, color, ox, oy, tw, th,
                        alpha_min, t_min, False)
        # the tile into the flat outputs: unsigned indices (no negative-index wraparound code) and
        # the channels spelt out (a loop over a runtime count would not unroll)
        for ly in range(th):
            row = np.uint64((oy + ly) * width + ox)
            for lx in range(tw):
                p = np.uint64(ly * TILE + lx)
                q = row + np.uint64(lx)
                trans = abs(st[p])
                if nch == 3:
                    rgb = np.uint64(3) * q
                    image[rgb] = st[_PLANE + p] + trans * bg0
                    image[rgb + np.uint64(1)] = st[np.uint64(2) * _PLANE + p] + trans * bg1
                    image[rgb + np.uint64(2)] = st[np.uint64(3) * _PLANE + p] + trans * bg2
                else:
                    image[q] = st[_PLANE + p] + trans * bg0
                a = np.float32(1.0) - trans
                alpha_out[q] = a
                if want_depth:
                    z = st[np.uint64(4) * _PLANE + p]
                    depth_out[q] = z / a if a > 0 else np.float32(0.0)


def rasterize_fast(means, quats, scales, opacities, colors, w2c, intrinsics: Intrinsics, *, background=None,
                   near: float = 0.01, return_depth: bool = False, return_alpha: bool = False,
                   alpha_min: float = ALPHA_MIN, t_min: float = T_MIN,
                   threads: int | None = None) -> RenderOutput:
    """Render Gaussians on the CPU; the arguments of ``rasterize`` as numpy (torch tensors accepted).

    means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 3] linear, opacities [N] in [0, 1],
    colors [N, C] or SH [N, K, C]; converted to float32. w2c [4, 4], intrinsics, background and
    near as in ``rasterize``. alpha_min: a splat is skipped where its alpha is below this;
    t_min: a pixel stops once blending would leave less transmittance than this.
    threads: threads for the blending (default: numba's, all cores); a service on a shared or
    small machine may prefer 1, as a preempted worker thread stalls the whole parallel region.
    Set for this call only (numba's thread count is per calling thread).
    returns RenderOutput of float32 numpy arrays: image [H, W, C], alpha [H, W] and depth [H, W]
    (expected camera z) when asked for.
    """
    arrays = as_float32_arrays(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors)
    chk = check_inputs(*arrays.values(), w2c, intrinsics, background, near)
    for name, value in (("alpha_min", alpha_min), ("t_min", t_min)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < ALPHA_MAX:
            raise InvalidInputError(f"{name} must be a number in [0, {ALPHA_MAX}), got {value!r}")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                or not 1 <= threads <= numba.config.NUMBA_NUM_THREADS):
        raise InvalidInputError(f"threads must be an integer in [1, {numba.config.NUMBA_NUM_THREADS}], "
                                f"got {threads!r}")
    width, height = intrinsics.width, intrinsics.height
    n = chk.means.shape[0]
    columns = np.empty((7, n), np.float32)  # _project's output, one row per quantity
    rect_columns = np.empty((4, n), np.int32)
    rows = [np.ascontiguousarray(a.T) for a in (chk.means, chk.quats, chk.scales)]
    with np.errstate(divide="ignore"):  # an opacity of 0: -inf, culled by alpha_min or of alpha 0
        log_o = np.log(chk.opacities.astype(np.float64))
    grid_x, grid_y = -(-width // TILE), -(-height // TILE)
    image = np.empty((height, width, chk.channels), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width) if return_depth else (0, 0), np.float32)
    previous_threads = numba.get_num_threads()
    try:
        if threads is not None:
            numba.set_num_threads(threads)
        _project(*rows, chk.opacities, log_o, chk.w2c, intrinsics.fx, intrinsics.fy, intrinsics.cx,
                 intrinsics.cy, width, height, float(near), float(alpha_min), columns, rect_columns)
        # the blending reads a splat's numbers together: one row per splat
        splat, rect = np.ascontiguousarray(columns[:6].T), np.ascontiguousarray(rect_columns.T)
        depth_key = columns[6]
        if chk.colors.ndim == 3:  # SH: the colour as seen from this camera
            color = np.zeros((n, chk.channels), np.float32)
            centre = np.ascontiguousarray(-(chk.w2c[:3, :3].T @ chk.w2c[:3, 3]), dtype=np.float64)
            _sh_colors(chk.colors, chk.means, centre, rect, color)
        else:
            color = chk.colors
        order = depth_order(rect, depth_key.view(np.uint32))
        start, ids = bin_tiles(rect, order, grid_x, grid_y)
        previous = numba.set_parallel_chunksize(1)  # work items go to threads one at a time
        try:
            _blend(start, ids, splat, depth_key, rect, color, chk.background, width, height, grid_x,
                   np.float32(alpha_min), np.float32(t_min), bool(return_depth), image.reshape(-1),
                   alpha.reshape(-1), depth.reshape(-1))
        finally:
            numba.set_parallel_chunksize(previous)
    finally:
        numba.set_num_threads(previous_threads)
    return RenderOutput(image=image, alpha=alpha if return_alpha else None,
                        depth=depth if return_depth else None)


KERNELS = (_project, _blend)
"""The kernels every render compiles on first use (``jit.compiled`` tells whether numba's cache has them)."""
COMPILE_S = 40
"""About how long numba compiles the renderer's kernels on a first run (2 shared cores: 35 to 49 s);
``edmcgs warm-up`` (run by setup) compiles them into numba's cache beforehand."""
