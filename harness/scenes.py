"""Random Gaussian scenes in front of a camera, for the rasterizer tests and the benchmark."""

import numpy as np

from edmcgs.geometry import Intrinsics, pose_from_quat, world_to_camera


def random_scene(n, width, height, *, seed=0, sh_degree=None, channels=3, px_sigma=(1.0, 6.0),
                 depth=(2.0, 6.0), opacity=(0.2, 0.95), margin=0.1):
    """n Gaussians spread over the view of a camera looking at them from a random pose.

    Screen sizes are drawn log-uniform in ``px_sigma`` (pixels, before the 0.3 px^2 low-pass);
    ``margin`` lets some spill past the image edges. Returns a dict of float64 numpy arrays and
    the camera: means, quats, scales, opacities, colors, w2c, intrinsics.
    """
    rng = np.random.default_rng(seed)
    f = 0.9 * width
    k = Intrinsics(f, f, (width - 1) / 2, (height - 1) / 2, width, height)
    z = rng.uniform(*depth, n)
    u = rng.uniform(-margin * width, (1 + margin) * width, n)
    v = rng.uniform(-margin * height, (1 + margin) * height, n)
    cam = np.stack([(u - k.cx) * z / f, (v - k.cy) * z / f, z], 1)
    sigma_px = np.exp(rng.uniform(*np.log(px_sigma), n))
    scales = (sigma_px * z / f)[:, None] * np.exp(rng.uniform(-0.7, 0.7, (n, 3)))
    q = rng.normal(size=(n, 4))
    q0 = q[0] if n else rng.normal(size=4)  # the camera's turn (an empty scene still has a camera)
    c2w = pose_from_quat(rng.normal(size=3), q0 / np.linalg.norm(q0))
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    quats = rng.normal(size=(n, 4))
    opac = rng.uniform(*opacity, n)
    if sh_degree is None:
        colors = rng.uniform(0, 1, (n, channels))
    else:
        colors = rng.normal(0, 0.5, (n, (sh_degree + 1) ** 2, channels))
    return dict(means=means, quats=quats, scales=scales, opacities=opac, colors=colors,
                w2c=world_to_camera(c2w), intrinsics=k)


def with_values(scene, **changes):
    """A copy of scene with arr[index] = value for each name=(index, value)."""
    out = dict(scene)
    for name, (index, value) in changes.items():
        arr = np.array(out[name], copy=True)
        arr[index] = value
        out[name] = arr
    return out


def at_camera_depth(scene, idx, z):
    """Move Gaussians idx to camera depth z (keeping their ray)."""
    w2c = scene["w2c"]
    means = np.array(scene["means"], copy=True)
    cam = means[idx] @ w2c[:3, :3].T + w2c[:3, 3]
    cam = cam * (np.asarray(z)[..., None] / cam[..., 2:3]) if np.all(cam[..., 2] != 0) else cam
    cam[..., 2] = z
    means[idx] = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    return dict(scene, means=means)
