"""Ray positional encoding (PETR-style, as the authors' ``AddRayPE``).

For every feature pixel (u, v), u = 0..w-1, v = 0..h-1 (no half-pixel offset), the ray
((u - cx) / fx, (v - cy) / fy, 1) of the feature-resolution camera is sampled at D depths
d_i = exp(ln near + ln(far / near) * i / (D - 1)) along the optical axis.  The points are taken
to the local (snippet) frame, each axis is mapped to [0, 1] with the ray scale, passed through
``inverse_sigmoid`` and flattened as (x0, y0, z0, x1, ...) into a 3D-vector, which an MLP
(Linear, ReLU, Linear) turns into a C-vector that is added to the image features.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def inverse_sigmoid(x: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """log(max(x, eps) / max(1 - x, eps)) after clamping x to [0, 1] (the authors' form)."""
    x = x.clamp(0.0, 1.0)
    return torch.log(x.clamp(min=eps) / (1.0 - x).clamp(min=eps))


def normalize_points(points: torch.Tensor, scale) -> torch.Tensor:
    """Metres in the local frame -> [0, 1] per axis; scale = [xmin, xmax, ymin, ymax, zmin, zmax]."""
    lo = points.new_tensor(scale[0::2])
    hi = points.new_tensor(scale[1::2])
    return (points - lo) / (hi - lo)


def denormalize_points(points: torch.Tensor, scale) -> torch.Tensor:
    lo = points.new_tensor(scale[0::2])
    hi = points.new_tensor(scale[1::2])
    return points * (hi - lo) + lo


class RayEncoder(nn.Module):
    """camera (..., N, 4) = (fx, fy, cx, cy) at feature resolution, T_local_camera (..., N, 4, 4)
    -> ray encoding (..., N, h, w, C)."""

    def __init__(self, feature_size: tuple, dim: int, samples: int, depth: tuple, scale):
        super().__init__()
        self.width, self.height = feature_size
        self.samples = samples
        self.scale = tuple(float(s) for s in scale)
        near, far = depth
        ramp = torch.linspace(0.0, 1.0, samples)
        depths = torch.exp(math.log(near) + math.log(far / near) * ramp)
        self.register_buffer("depths", depths, persistent=False)
        u = torch.arange(self.width, dtype=torch.float32)
        v = torch.arange(self.height, dtype=torch.float32)
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        self.register_buffer("pixels", torch.stack([uu, vv], -1), persistent=False)  # (h, w, 2)
        self.mlp = nn.Sequential(nn.Linear(3 * samples, dim), nn.ReLU(), nn.Linear(dim, dim))

    def ray_directions(self, camera: torch.Tensor, T_local_camera: torch.Tensor) -> torch.Tensor:
        """Every feature pixel's ray at unit depth, in the local frame: (..., N, h, w, 3, 1)."""
        f = camera[..., None, None, 0:2]
        c = camera[..., None, None, 2:4]
        xy = (self.pixels - c) / f                                    # (..., N, h, w, 2)
        rays_camera = torch.cat([xy, torch.ones_like(xy[..., :1])], -1)
        R = T_local_camera[..., None, None, :3, :3]
        return R @ rays_camera[..., None]

    def ray_points(self, camera: torch.Tensor, T_local_camera: torch.Tensor) -> torch.Tensor:
        """Sample points of every feature pixel's ray in the local frame: (..., N, h, w, D, 3)."""
        t = T_local_camera[..., None, None, None, :3, 3]
        directions_local = self.ray_directions(camera, T_local_camera)[..., 0]  # (.., h, w, 3)
        return directions_local[..., None, :] * self.depths[:, None] + t

    def hidden(self, camera: torch.Tensor, T_local_camera: torch.Tensor) -> torch.Tensor:
        """The MLP's hidden layer, ReLU(Linear(points)): (..., N, h, w, C).  The encoding is
        ``mlp[2]`` of it; the exported graphs keep it in this factored form (see
        ``parq_export.factored``)."""
        points = inverse_sigmoid(normalize_points(self.ray_points(camera, T_local_camera),
                                                  self.scale))
        points = points.flatten(-2)                                   # (..., N, h, w, 3D)
        # As one 2-D matrix the Linear layer exports as Gemm with the bias (and the ReLU)
        # fused, instead of MatMul + a separate Add over the (N h w, C) result.
        hidden = self.mlp[1](self.mlp[0](points.reshape(-1, points.shape[-1])))
        return hidden.reshape(*points.shape[:-1], hidden.shape[-1])

    def hidden_coordinate_major(self, camera: torch.Tensor,
                                T_local_camera: torch.Tensor) -> torch.Tensor:
        """:meth:`hidden`, equal up to float rounding, in the arrangement the exported backbone
        uses.  The points are formed coordinate-major, (..., N, h, w, 3, D), as
        d_i * direction / span + (t - lo) / span: every pass over them broadcasts along the
        contiguous depth axis.  In :meth:`hidden`'s (..., D, 3) order, four passes broadcast
        along an inner axis of 3, which onnxruntime does element by element: 42 ms of the
        authors' backbone on 2 AVX2 cores (profiled), against 3 ms for a plain pass.  The first
        Linear layer's columns are permuted to match.  Training keeps :meth:`hidden`, so that
        a seeded run rebuilds the same weights."""
        directions_local = self.ray_directions(camera, T_local_camera)  # (..., N, h, w, 3, 1)
        lo = camera.new_tensor(self.scale[0::2])[:, None]              # (3, 1)
        span = camera.new_tensor(self.scale[1::2])[:, None] - lo
        t = T_local_camera[..., None, None, :3, 3:4]                  # (..., N, 1, 1, 3, 1)
        points = directions_local / span * self.depths + (t - lo) / span  # (..., N, h, w, 3, D)
        points = inverse_sigmoid(points).flatten(-2)                  # (x0..xD-1, y0.., z0..)
        linear = self.mlp[0]
        D = self.samples
        weight = linear.weight.reshape(-1, D, 3).transpose(1, 2).reshape(-1, 3 * D)
        hidden = torch.relu(F.linear(points.reshape(-1, 3 * D), weight, linear.bias))
        return hidden.reshape(*points.shape[:-1], hidden.shape[-1])

    def forward(self, camera: torch.Tensor, T_local_camera: torch.Tensor) -> torch.Tensor:
        hidden = self.hidden(camera, T_local_camera)
        encoding = self.mlp[2](hidden.reshape(-1, hidden.shape[-1]))
        return encoding.reshape(hidden.shape)
