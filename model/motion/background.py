"""A distant background layer: a learned texture over world ray directions, behind all Gaussians.

A static or purely rotating camera sees its static scene as if at infinite distance: the colour of a
pixel is a function of its ray's direction only. The layer stores that function as an image on the
*reference* camera's image plane (the first anchor's rotation and intrinsics), widened to hold every
direction the recording's cameras look along (a pan), at one texel per reference pixel. A pixel of any
camera reads it where its ray crosses that plane (bilinear); for the reference camera itself, and any
camera with its rotation and intrinsics, that is the texel at the pixel's own integer position, read
without interpolation. Renders composite it under the splats:

    image = rgb_gaussians + (1 - alpha_gaussians) * texture(ray)

The Gaussians (and their control points) are then left for what moves. The texture starts from the
per-texel median of the anchors (which drops a passing car and averages read noise) and is fitted with
the Gaussians by the photometric loss.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from edmcgs.geometry import Intrinsics

MARGIN = 2
"""Texels beyond the outermost projected pixel on each side (bilinear reads at the edge stay inside)."""


MEDIAN_BAND_BYTES = 64 << 20
"""Memory the samples of one band of texture rows may take while the median is fitted (the texture of a
moving camera's 151 anchors took about 2 GB whole)."""


class BackgroundLayer(nn.Module):
    """Texture [C, Ht, Wt] on the reference image plane; texel (i, j) is reference pixel (u0 + j, v0 + i).

    Buffers: ``ref_rot`` [3, 3] reference camera-to-world rotation, ``ref_k`` [4] (fx, fy, cx, cy),
    ``origin`` [2] (u0, v0). Parameter: ``texture`` (logits of the colour, colour = sigmoid).
    """

    def __init__(self, texture_logits: Tensor, ref_rot: Tensor, ref_k: Tensor, origin: Tensor):
        super().__init__()
        self.texture = nn.Parameter(texture_logits)
        self.register_buffer("ref_rot", ref_rot.double().reshape(3, 3))
        self.register_buffer("ref_k", ref_k.double().reshape(4))
        self.register_buffer("origin", origin.double().reshape(2))
        self._host_copy: tuple | None = None
        self._axes: tuple | None = None

    @classmethod
    def empty(cls, channels: int, height: int, width: int) -> BackgroundLayer:
        """Placeholders of the right shapes for loading a checkpoint."""
        return cls(torch.zeros(channels, height, width), torch.eye(3), torch.zeros(4), torch.zeros(2))

    @classmethod
    def covering(cls, rotations: np.ndarray, intr: Intrinsics, channels: int) -> BackgroundLayer:
        """A grey (0.5) layer whose plane holds every pixel of cameras with ``rotations`` [F, 3, 3] (c2w).

        The reference is the first rotation; rays of a camera turned by 90 degrees or more from it
        cannot meet its plane and are clamped to the texture's edge (a pan of that size is out of scope).
        """
        rots = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        ref = rots[0]
        corners = np.array([[0, 0, 1], [intr.width - 1, 0, 1], [0, intr.height - 1, 1],
                            [intr.width - 1, intr.height - 1, 1]], dtype=np.float64)
        kinv = np.linalg.inv(np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]]))
        rays = corners @ kinv.T                                           # [4, 3]
        d = np.einsum("ij,fjk,nk->fni", ref.T, rots, rays).reshape(-1, 3)  # into the reference frame
        d = d[d[:, 2] > 1e-6]
        u = intr.fx * d[:, 0] / d[:, 2] + intr.cx
        v = intr.fy * d[:, 1] / d[:, 2] + intr.cy
        w1, h1 = intr.width - 1, intr.height - 1
        u0 = math.floor(min(u.min(), 0.0) + 1e-6) - (MARGIN if u.min() < -1e-6 else 0)
        v0 = math.floor(min(v.min(), 0.0) + 1e-6) - (MARGIN if v.min() < -1e-6 else 0)
        u1 = math.ceil(max(u.max(), w1) - 1e-6) + (MARGIN if u.max() > w1 + 1e-6 else 0)
        v1 = math.ceil(max(v.max(), h1) - 1e-6) + (MARGIN if v.max() > h1 + 1e-6 else 0)
        width, height = int(u1 - u0 + 1), int(v1 - v0 + 1)
        return cls(torch.zeros(channels, height, width), torch.from_numpy(ref),
                   torch.tensor([intr.fx, intr.fy, intr.cx, intr.cy]), torch.tensor([float(u0), float(v0)]))

    @property
    def channels(self) -> int:
        return int(self.texture.shape[0])

    def colors(self) -> Tensor:
        """[C, Ht, Wt] the texture's colour in (0, 1)."""
        return torch.sigmoid(self.texture)

    def texel_grid(self, c2w_rot: Tensor | np.ndarray, intr: Intrinsics) -> Tensor | None:
        """[H, W, 2] float32 ``grid_sample`` coordinates (align_corners, [-1, 1] over the texture) of a
        camera's pixels, or None when the camera has the reference's rotation and intrinsics (pixel
        (u, v) is texel (u - u0, v - v0)). Pixel -> reference plane -> texel is one homography, so it is
        built as a 3x3 matrix and applied to the pixel grid's rows and columns by broadcasting."""
        ref_rot, k, origin = self._host()
        same_k = np.allclose(k, [intr.fx, intr.fy, intr.cx, intr.cy], rtol=0, atol=1e-9)
        dev = self.ref_rot.device
        rot = (c2w_rot.detach().double().cpu().numpy() if isinstance(c2w_rot, Tensor)
               else np.asarray(c2w_rot, dtype=np.float64)).reshape(3, 3)
        if same_k and np.allclose(rot, ref_rot, rtol=0, atol=1e-12):
            return None
        _, ht, wt = self.texture.shape
        sx, sy = 2.0 / max(wt - 1, 1), 2.0 / max(ht - 1, 1)
        # the reference camera's K, the texture's origin and the grid's scale: affine, so exact before
        # the divide
        to_grid = np.array([[sx * k[0], 0.0, sx * (k[2] - origin[0]) - 1.0],
                            [0.0, sy * k[1], sy * (k[3] - origin[1]) - 1.0], [0.0, 0.0, 1.0]])
        from_pixel = np.array([[1.0 / intr.fx, 0.0, -intr.cx / intr.fx],
                               [0.0, 1.0 / intr.fy, -intr.cy / intr.fy], [0.0, 0.0, 1.0]])
        h = (to_grid @ (ref_rot.T @ rot) @ from_pixel).tolist()
        # composed in float64 on the host, applied in float32: to 1e-3 of a texel, in a third of the time
        # of float64 (a moving camera's render pays it every frame)
        u, v = self._pixel_axes(intr.width, intr.height, dev)
        z = (h[2][0] * u + h[2][1] * v + h[2][2]).clamp_min_(1e-6)  # 90 degrees or more away: the edge
        grid = torch.empty(intr.height, intr.width, 2, device=dev)
        torch.div(h[0][0] * u + h[0][1] * v + h[0][2], z, out=grid[..., 0])
        torch.div(h[1][0] * u + h[1][1] * v + h[1][2], z, out=grid[..., 1])
        return grid

    def _pixel_axes(self, width: int, height: int, device) -> tuple[Tensor, Tensor]:
        """float32 pixel columns [1, W] and rows [H, 1] (one size kept: a client asking many costs none)."""
        key = (width, height, str(device))
        if self._axes is None or self._axes[0] != key:
            self._axes = (key, torch.arange(width, dtype=torch.float32, device=device)[None, :],
                          torch.arange(height, dtype=torch.float32, device=device)[:, None])
        return self._axes[1], self._axes[2]

    def _host(self) -> tuple[np.ndarray, list[float], list[float]]:
        """(ref_rot, ref_k, origin) on the host, read from the buffers once per change of them (a load
        or a move copies into them or replaces them; the cache holds the tensors, so ids stay unique)."""
        bufs = (self.ref_rot, self.ref_k, self.origin)
        key = tuple((id(b), b._version) for b in bufs)
        if self._host_copy is None or self._host_copy[0] != key:
            self._host_copy = (key, bufs, (self.ref_rot.cpu().numpy().copy(), self.ref_k.tolist(),
                                           self.origin.tolist()))
        return self._host_copy[2]

    def image(self, c2w_rot: Tensor | np.ndarray, intr: Intrinsics) -> Tensor:
        """[H, W, C]: the layer seen by a camera with rotation ``c2w_rot`` [3, 3] and intrinsics ``intr``."""
        tex = self.colors()
        grid = self.texel_grid(c2w_rot, intr)
        if grid is None:
            u0, v0 = (-round(x) for x in self._host()[2])
            return tex[:, v0:v0 + intr.height, u0:u0 + intr.width].permute(1, 2, 0)
        out = F.grid_sample(tex[None], grid[None].to(tex.dtype), mode="bilinear", padding_mode="border",
                            align_corners=True)
        return out[0].permute(1, 2, 0)

    @torch.no_grad()
    def fit_median(self, images: np.ndarray, rotations: np.ndarray, intr: Intrinsics, *,
                   band_bytes: int = MEDIAN_BAND_BYTES) -> None:
        """Set the texture to the per-texel median of ``images`` [F, H, W, C] uint8 seen by cameras with
        ``rotations`` [F, 3, 3]; texels no image sees take the median of all pixels. Bands of texture
        rows at a time, each holding every image's samples in at most about ``band_bytes``."""
        channels, ht, wt = self.texture.shape
        rotations = np.asarray(rotations, dtype=np.float64)
        fallback = np.median(images.reshape(-1, images.shape[-1]), 0).astype(np.float32) / 255
        fallback = torch.from_numpy(fallback)[:, None, None]
        sources = [torch.from_numpy(img.astype(np.float32) / 255.0).permute(2, 0, 1)[None] for img in images]
        to_camera = [(torch.from_numpy(rot).T @ self.ref_rot).T for rot in rotations]  # reference -> camera
        k = self.ref_k.tolist()
        band = max(1, int(band_bytes) // max(1, len(images) * channels * wt * 4))
        for top in range(0, ht, band):
            rows = min(band, ht - top)
            vv, uu = torch.meshgrid(torch.arange(top, top + rows, dtype=torch.float64),
                                    torch.arange(wt, dtype=torch.float64), indexing="ij")
            u_ref, v_ref = uu + self.origin[0], vv + self.origin[1]
            rays = torch.stack([(u_ref - k[2]) / k[0], (v_ref - k[3]) / k[1], torch.ones_like(u_ref)], -1)
            stack = torch.empty(len(images), channels, rows, wt)
            for i, (src, rot) in enumerate(zip(sources, to_camera, strict=True)):
                d = rays @ rot
                z = d[..., 2]
                u = intr.fx * d[..., 0] / z.clamp_min(1e-6) + intr.cx
                v = intr.fy * d[..., 1] / z.clamp_min(1e-6) + intr.cy
                inside = (z > 1e-6) & (u >= -0.5) & (u <= intr.width - 0.5) & (v >= -0.5) \
                    & (v <= intr.height - 0.5)
                grid = torch.stack([(2 * u + 1) / intr.width - 1, (2 * v + 1) / intr.height - 1], -1).float()
                val = F.grid_sample(src, grid[None], mode="bilinear", padding_mode="border",
                                    align_corners=False)[0]
                stack[i] = val.masked_fill_(~inside[None], float("nan"))
            med = torch.nanmedian(stack, dim=0).values                  # [C, rows, Wt]
            med = torch.where(torch.isnan(med), fallback.expand_as(med), med)
            self.texture[:, top:top + rows].copy_(torch.logit(med.clamp(0.01, 0.99)))


def composite(image: Tensor, alpha: Tensor, background: Tensor) -> Tensor:
    """Gaussians rendered over black, [H, W, C] with alpha [H, W], over a [H, W, C] background."""
    return image + (1.0 - alpha)[..., None] * background
