"""A brute-force float64 3DGS renderer: every pixel against every Gaussian, written from the 3DGS
description and independent of edmcgs.model's rasterizers (it shares no code with them).

Same math: EWA projection with the Jacobian's x/z, y/z clamped to the frustum widened by 0.3 tan,
a 0.3 px^2 low-pass, radius ceil(3 sqrt(lambda_max)) with lambda_max = mid + sqrt(max(0.1, mid^2 - det)),
16x16 tiles (a pixel considers a Gaussian iff the pixel's tile is in the Gaussian's tile rectangle),
depth order (stable), alpha = min(0.99, o exp(power)), alpha < alpha_min skipped, a pixel stops
when T (1 - alpha) would fall below t_min; SH colour + 0.5 clamped at 0; pixel centres at integers.
"""

import math

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435]


def eval_sh(sh, d):
    """sh [K, C], d unit [3] -> [C] (3DGS eval_sh, without the +0.5)."""
    k = sh.shape[0]
    x, y, z = d
    res = C0 * sh[0]
    if k > 1:
        res = res - C1 * y * sh[1] + C1 * z * sh[2] - C1 * x * sh[3]
    if k > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        res = (res + C2[0] * xy * sh[4] + C2[1] * yz * sh[5] + C2[2] * (2 * zz - xx - yy) * sh[6]
               + C2[3] * xz * sh[7] + C2[4] * (xx - yy) * sh[8])
    if k > 9:
        res = (res + C3[0] * y * (3 * xx - yy) * sh[9] + C3[1] * xy * z * sh[10]
               + C3[2] * y * (4 * zz - xx - yy) * sh[11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[12]
               + C3[4] * x * (4 * zz - xx - yy) * sh[13] + C3[5] * z * (xx - yy) * sh[14]
               + C3[6] * x * (xx - 3 * yy) * sh[15])
    return res


def rotmat(q):
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def render(means, quats, scales, opacities, colors, w2c, fx, fy, cx, cy, width, height, *,
           background=None, near=0.01, alpha_min=1 / 255, t_min=1e-4):
    """Returns (image [H, W, C], alpha [H, W], depth [H, W]) as float64 numpy."""
    means, quats, scales = (np.asarray(a, np.float64) for a in (means, quats, scales))
    opacities, colors, w2c = (np.asarray(a, np.float64) for a in (opacities, colors, w2c))
    channels = colors.shape[-1]
    bg = np.zeros(channels) if background is None else np.broadcast_to(np.asarray(background, np.float64),
                                                                         (channels,))
    R, t = w2c[:3, :3], w2c[:3, 3]
    centre = -R.T @ t
    grid_x, grid_y = math.ceil(width / 16), math.ceil(height / 16)
    tanx, tany = 0.5 * width / fx, 0.5 * height / fy
    splats = []
    for i in range(len(means)):
        x, y, z = R @ means[i] + t
        if z <= near:
            continue
        u, v = fx * x / z + cx, fy * y / z + cy
        xz = min((width - cx) / fx + 0.3 * tanx, max(-(cx / fx + 0.3 * tanx), x / z))
        yz = min((height - cy) / fy + 0.3 * tany, max(-(cy / fy + 0.3 * tany), y / z))
        J = np.array([[fx / z, 0, -fx * xz / z], [0, fy / z, -fy * yz / z]])
        Rg = rotmat(quats[i])
        cov3 = Rg @ np.diag(scales[i] ** 2) @ Rg.T
        cov = J @ R @ cov3 @ R.T @ J.T + 0.3 * np.eye(2)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        conic = np.array([cov[1, 1], -cov[0, 1], cov[0, 0]]) / det
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        r = math.ceil(3 * math.sqrt(lam))
        rect = (min(grid_x, max(0, math.floor((u - r) / 16))),
                min(grid_y, max(0, math.floor((v - r) / 16))),
                min(grid_x, max(0, math.floor((u + r) / 16) + 1)),
                min(grid_y, max(0, math.floor((v + r) / 16) + 1)))
        if rect[2] <= rect[0] or rect[3] <= rect[1]:
            continue
        if colors.ndim == 3:
            d = means[i] - centre
            col = np.maximum(eval_sh(colors[i], d / np.linalg.norm(d)) + 0.5, 0.0)
        else:
            col = colors[i]
        splats.append((z, i, u, v, conic, rect, col))
    splats.sort(key=lambda s: s[0])  # stable: ties keep index order

    vv, uu = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64),
                         indexing="ij")
    tile_x, tile_y = (uu // 16).astype(int), (vv // 16).astype(int)
    T = np.ones((height, width))
    acc = np.zeros((height, width, channels))
    dep = np.zeros((height, width))
    done = np.zeros((height, width), bool)
    for z, i, u, v, (A, B, Cc), rect, col in splats:
        inside = (tile_x >= rect[0]) & (tile_x < rect[2]) & (tile_y >= rect[1]) & (tile_y < rect[3])
        dx, dy = uu - u, vv - v
        power = -0.5 * (A * dx * dx + Cc * dy * dy) - B * dx * dy
        alpha = np.minimum(0.99, opacities[i] * np.exp(power))
        use = inside & ~done & (alpha >= alpha_min)
        test_t = T * (1 - alpha)
        stop = use & (test_t < t_min)
        done |= stop
        use &= ~stop
        w = np.where(use, alpha * T, 0.0)
        acc += w[..., None] * col
        dep += w * z
        T = np.where(use, test_t, T)
    alpha_img = 1 - T
    depth = np.where(alpha_img > 0, dep / np.where(alpha_img > 0, alpha_img, 1), 0.0)
    return acc + T[..., None] * bg, alpha_img, depth


def render_camera(arrays, w2c, intrinsics, **kwargs):
    """``render`` of the five Gaussian arrays (means, quats, scales, opacities, colors) seen by a camera
    with ``intrinsics`` (anything with fx, fy, cx, cy, width, height)."""
    k = intrinsics
    return render(*arrays, w2c, k.fx, k.fy, k.cx, k.cy, k.width, k.height, **kwargs)
