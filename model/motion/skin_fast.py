"""The CPU kernel of inference skinning (numba): ``skin_plan.skin``'s blend in one pass per Gaussian.

Torch spends most of a CPU deformation gathering and reducing [N, K, 12] temporaries; this loop reads
each Gaussian's K affine maps and quaternions once and writes its mean and rotation (float64 inside,
float32 out). Imported only at inference on the CPU: training never loads numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from edmcgs.geometry import rotmat_entries

_rotmat = numba.njit(inline="always")(rotmat_entries)


@numba.njit(cache=True, nogil=True, parallel=True)
def blend(means, quats, bind, weights, control, rotations, translations, moving, out_means, out_quats):
    """Skin Gaussians ``moving[j]`` (all when ``moving`` is empty) into ``out_means``/``out_quats``.

    means: [N, 3], quats: [N, 4] unit (w, x, y, z) canonical; bind, weights: [Nm, K] (row j belongs to
    Gaussian moving[j]); control: [M, 3] canonical control points p, rotations: [M, 4] unit,
    translations: [M, 3] (each point's map x -> R (x - p) + p + T, as ``skinning.control_affine``).
    out_means, out_quats: [N, 3], [N, 4], already holding the canonical values of the others.
    Parallel over Gaussians (each writes only its own rows).
    """
    m = control.shape[0]
    affine = np.empty((m, 12))  # row-major 3x4 maps (R | p + T - R p), in float64
    for c in range(m):
        r = _rotmat(np.float64(rotations[c, 0]), np.float64(rotations[c, 1]), np.float64(rotations[c, 2]),
                    np.float64(rotations[c, 3]))
        p0, p1, p2 = np.float64(control[c, 0]), np.float64(control[c, 1]), np.float64(control[c, 2])
        for row in range(3):
            affine[c, 4 * row] = r[3 * row]
            affine[c, 4 * row + 1] = r[3 * row + 1]
            affine[c, 4 * row + 2] = r[3 * row + 2]
            affine[c, 4 * row + 3] = (np.float64(control[c, row]) + np.float64(translations[c, row])
                                      - (r[3 * row] * p0 + r[3 * row + 1] * p1 + r[3 * row + 2] * p2))
    nm, k = bind.shape
    for j in numba.prange(nm):
        i = np.int64(moving[j]) if moving.shape[0] > 0 else np.int64(j)
        x, y, z = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
        # the blended map applied to the mean, row by row: sum_s w_s (A_s [x y z 1])
        m0 = m1 = m2 = 0.0
        q0 = q1 = q2 = q3 = 0.0
        for s in range(k):
            c = bind[j, s]
            w = np.float64(weights[j, s])
            m0 += w * (affine[c, 0] * x + affine[c, 1] * y + affine[c, 2] * z + affine[c, 3])
            m1 += w * (affine[c, 4] * x + affine[c, 5] * y + affine[c, 6] * z + affine[c, 7])
            m2 += w * (affine[c, 8] * x + affine[c, 9] * y + affine[c, 10] * z + affine[c, 11])
            q0 += w * rotations[c, 0]
            q1 += w * rotations[c, 1]
            q2 += w * rotations[c, 2]
            q3 += w * rotations[c, 3]
        out_means[i, 0] = m0
        out_means[i, 1] = m1
        out_means[i, 2] = m2
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
