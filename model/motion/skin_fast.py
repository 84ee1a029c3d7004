"""The CPU kernel of inference skinning (numba): ``skin_plan.skin``'s blend in one pass per Gaussian.

Torch spends most of a CPU deformation gathering and reducing [N, K, 12] temporaries; this loop reads
each Gaussian's K affine maps and quaternions once and writes its mean and rotation (float64 inside,
float32 out). Imported only at inference on the CPU: training never loads numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def blend(means, quats, bind, weights, affine, rotations, moving, out_means, out_quats):
    """Skin Gaussians ``moving[j]`` (all when ``moving`` is empty) into ``out_means``/``out_quats``.

    means: [N, 3], quats: [N, 4] unit (w, x, y, z) canonical; bind, weights: [Nm, K] (row j belongs to
    Gaussian moving[j]); affine: [M, 12] row-major 3x4 maps (R | p + T - R p); rotations: [M, 4] unit.
    out_means, out_quats: [N, 3], [N, 4], already holding the canonical values of the others.
    """
    nm, k = bind.shape
    for j in range(nm):
        i = moving[j] if moving.shape[0] > 0 else j
        a = np.zeros(12)
        q0 = q1 = q2 = q3 = 0.0
        for s in range(k):
            c = bind[j, s]
            w = np.float64(weights[j, s])
            for e in range(12):
                a[e] += w * affine[c, e]
            q0 += w * rotations[c, 0]
            q1 += w * rotations[c, 1]
            q2 += w * rotations[c, 2]
            q3 += w * rotations[c, 3]
        x, y, z = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        out_means[i, 0] = a[0] * x + a[1] * y + a[2] * z + a[3]
        out_means[i, 1] = a[4] * x + a[5] * y + a[6] * z + a[7]
        out_means[i, 2] = a[8] * x + a[9] * y + a[10] * z + a[11]
        norm = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        if norm > 1e-12:
            q0, q1, q2, q3 = q0 / norm, q1 / norm, q2 / norm, q3 / norm
        else:
            q0, q1, q2, q3 = 1.0, 0.0, 0.0, 0.0
        bw, bx, by, bz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), \
            np.float64(quats[i, 3])
        out_quats[i, 0] = q0 * bw - q1 * bx - q2 * by - q3 * bz
        out_quats[i, 1] = q0 * bx + q1 * bw + q2 * bz - q3 * by
        out_quats[i, 2] = q0 * by - q1 * bz + q2 * bw + q3 * bx
        out_quats[i, 3] = q0 * bz + q1 * by - q2 * bx + q3 * bw
