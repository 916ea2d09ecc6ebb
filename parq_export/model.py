"""The PARQ model in plain PyTorch: the reference the exported graphs are checked against, and
the network that ``parq_train`` trains.

Shapes: B snippets of N views, images (B, N, 3, H, W) RGB in [0, 1]; cameras (B, N, 4) =
(fx, fy, cx, cy) at feature resolution (stride 4, see ``parq_runtime.geometry.scale_camera``);
T_local_camera (B, N, 4, 4); features (B, N, C, h, w); memory (B, N, h, w, C) with tokens
ordered (view, row, column) when flattened.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .backbone import ResNetFPN
from .config import PARQConfig
from .layer import PARQLayer
from .ray_encoding import RayEncoder, denormalize_points


def pixel_aligned_features(memory: torch.Tensor, points_local: torch.Tensor,
                           camera: torch.Tensor, T_camera_local: torch.Tensor,
                           eps: float = 1e-3) -> torch.Tensor:
    """Query content: bilinear samples of the memory where the points project, averaged over the
    views where they are visible (the authors' ``project``).

    memory (B, N, h, w, C), points_local (B, K, 3) metres, camera (B, N, 4),
    T_camera_local (B, N, 4, 4) -> (B, K, C).  Samples use align_corners=True with zero padding
    and are summed over *all* views (a point just outside a view still picks up the border
    pixels' share), then divided by the number of views where the point is valid (at least 1).
    """
    B, N, h, w, C = memory.shape
    R = T_camera_local[..., :3, :3]
    t = T_camera_local[..., :3, 3]
    points_camera = points_local[:, None] @ R.transpose(-1, -2) + t[:, :, None]   # (B, N, K, 3)
    z = points_camera[..., 2]
    zc = z.clamp(min=eps)
    u = points_camera[..., 0] / zc * camera[..., 0:1] + camera[..., 2:3]
    v = points_camera[..., 1] / zc * camera[..., 1:2] + camera[..., 3:4]
    valid = (z > eps) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    grid = torch.stack([2 * u / (w - 1) - 1, 2 * v / (h - 1) - 1], -1)         # (B, N, K, 2)
    sampled = F.grid_sample(memory.reshape(B * N, h, w, C).permute(0, 3, 1, 2),
                            grid.reshape(B * N, 1, -1, 2), padding_mode="zeros",
                            align_corners=True)                               # (BN, C, 1, K)
    sampled = sampled.reshape(B, N, C, -1).sum(1).transpose(1, 2)            # (B, K, C)
    count = valid.sum(1).clamp(min=1).to(sampled.dtype)
    return sampled / count[..., None]


class PARQ(nn.Module):
    """ResNet-FPN + ray encoding + one recurrent PARQ layer + learned reference points."""

    def __init__(self, config: PARQConfig = PARQConfig()):
        super().__init__()
        c = config
        self.config = c
        self.backbone = ResNetFPN(c.resnet_depth, c.resnet_width, c.fpn_channels,
                                  c.pixel_mean, c.pixel_std)
        self.ray_encoder = RayEncoder(c.feature_size, c.feature_dim, c.ray_samples,
                                      c.ray_depth, c.ray_scale)
        self.layer = PARQLayer(c.feature_dim, c.heads, c.ffn_dim, len(c.classes),
                               c.mean_sizes, c.decoder_scale)
        self.refpoint = nn.Embedding(c.num_queries, 3)

    def initial_reference_points(self) -> torch.Tensor:
        """The learned reference points (K, 3), normalised to [0, 1]^3."""
        return self.refpoint.weight.sigmoid()

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """(B, N, 3, H, W) -> (B, N, C, h, w): the per-image part, independent of poses."""
        B, N = images.shape[:2]
        features = self.backbone(images.flatten(0, 1))
        return features.reshape(B, N, *features.shape[1:])

    def memory(self, features, camera, T_local_camera) -> torch.Tensor:
        """Features (B, N, C, h, w) + ray encoding -> memory (B, N, h, w, C)."""
        return features.permute(0, 1, 3, 4, 2) + self.ray_encoder(camera, T_local_camera)

    def forward(self, images, camera, T_local_camera, iterations=None, reference_points=None,
                form: str = "reference", extra_points=None) -> list:
        """Run the detector on B snippets; returns one dict per iteration (see PARQLayer), plus
        ``reference`` (B, K, 3): the point the iteration started from, metres.

        extra_points (B, D, 3), normalised: training's denoising queries
        (``parq_train.denoise``), appended after the K queries and iterated with them; the K
        queries do not attend to them, each attends only to the K queries and itself, and the
        heads decode them apart, so the K queries' outputs are what they are without them.
        Outputs then have K + D queries.

        form: ``reference`` recomputes the cross-attention keys and values at every iteration
        (the authors' way); ``cached`` projects them once; ``folded`` never projects the memory;
        ``fused`` is ``cached`` with torch's fused attention kernel (training).
        """
        iterations = self.config.iterations if iterations is None else iterations
        memory = self.memory(self.image_features(images), camera, T_local_camera)
        T_camera_local = torch.linalg.inv(T_local_camera)
        B = memory.shape[0]
        if reference_points is None:
            reference_points = self.initial_reference_points()
        ref = reference_points.expand(B, -1, -1) if reference_points.dim() == 2 \
            else reference_points
        self_mask = split = None
        if extra_points is not None:
            K, D = ref.shape[1], extra_points.shape[1]
            split = K
            ref = torch.cat([ref, extra_points.to(ref.dtype)], 1)
            self_mask = torch.ones(K + D, K + D, dtype=torch.bool, device=ref.device)
            self_mask[:, :K] = False
            self_mask[K:, K:] = ~torch.eye(D, dtype=torch.bool, device=ref.device)
        tokens = memory.flatten(1, 3)                                  # (B, S, C)
        operands = None
        if form != "reference":
            operands = self.layer.attention_operands(tokens, cached=(form != "folded"),
                                                     fused=(form == "fused"))
        outputs = []
        for _ in range(iterations):
            points = denormalize_points(ref, self.config.decoder_scale)
            content = pixel_aligned_features(memory, points, camera, T_camera_local)
            if form == "reference":
                out = self.layer(content, ref, memory=tokens, self_mask=self_mask, split=split)
            else:
                out = self.layer(content, ref, operands=operands, self_mask=self_mask,
                                 split=split)
            out["reference"] = points
            outputs.append(out)
            ref = out["next_reference_points"].detach()
        return outputs
