"""ResNet-FPN image encoder with torchvision's parameter names.

torchvision is not a dependency (its wheels do not import beside the pinned CPU torch), so the
network of ``torchvision.models.detection.backbone_utils.resnet_fpn_backbone`` is written out
here.  Parameter names match torchvision's ``BackboneWithFPN`` (``body.layer1.0.conv1.weight``,
``fpn.inner_blocks.0.0.weight`` ...), so a torchvision or PARQ state dict loads unchanged.

Shapes: images (B, 3, H, W) -> features (B, 4 * fpn_channels, H/4, W/4): the FPN outputs
P2..P5 each resized to P2's size (bilinear, align_corners=False) and concatenated, as the
authors' ``ResnetFPN`` does.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class FrozenBatchNorm2d(nn.Module):
    """BatchNorm with fixed statistics (torchvision.ops.FrozenBatchNorm2d, eps=1e-5).

    Holds weight, bias, running_mean, running_var as buffers (no num_batches_tracked).
    """

    def __init__(self, num_features: int, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.register_buffer("weight", torch.ones(num_features))
        self.register_buffer("bias", torch.zeros(num_features))
        self.register_buffer("running_mean", torch.zeros(num_features))
        self.register_buffer("running_var", torch.ones(num_features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale = self.weight * (self.running_var + self.eps).rsqrt()
        bias = self.bias - self.running_mean * scale
        return x * scale.reshape(1, -1, 1, 1) + bias.reshape(1, -1, 1, 1)


def conv3x3(cin, cout, stride=1):
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


def conv1x1(cin, cout, stride=1):
    return nn.Conv2d(cin, cout, 1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin, width, stride=1, downsample=None, norm=FrozenBatchNorm2d):
        super().__init__()
        self.conv1 = conv3x3(cin, width, stride)
        self.bn1 = norm(width)
        self.conv2 = conv3x3(width, width)
        self.bn2 = norm(width)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """ResNet v1.5 bottleneck: the stride sits on the 3x3 convolution, as in torchvision."""

    expansion = 4

    def __init__(self, cin, width, stride=1, downsample=None, norm=FrozenBatchNorm2d):
        super().__init__()
        self.conv1 = conv1x1(cin, width)
        self.bn1 = norm(width)
        self.conv2 = conv3x3(width, width, stride)
        self.bn2 = norm(width)
        self.conv3 = conv1x1(width, width * self.expansion)
        self.bn3 = norm(width * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


RESNET_LAYOUT = {18: (BasicBlock, (2, 2, 2, 2)), 34: (BasicBlock, (3, 4, 6, 3)),
                 50: (Bottleneck, (3, 4, 6, 3)), 101: (Bottleneck, (3, 4, 23, 3))}


class ResNetBody(nn.Module):
    """ResNet without avgpool/fc; returns layer1..layer4 outputs (strides 4, 8, 16, 32)."""

    def __init__(self, depth: int = 50, width: int = 64):
        super().__init__()
        block, counts = RESNET_LAYOUT[depth]
        self.conv1 = nn.Conv2d(3, width, 7, stride=2, padding=3, bias=False)
        self.bn1 = FrozenBatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        cin = width
        for i, n in enumerate(counts):
            w = width * 2 ** i
            stride = 1 if i == 0 else 2
            downsample = None
            if stride != 1 or cin != w * block.expansion:
                downsample = nn.Sequential(conv1x1(cin, w * block.expansion, stride),
                                           FrozenBatchNorm2d(w * block.expansion))
            blocks = [block(cin, w, stride, downsample)]
            cin = w * block.expansion
            blocks += [block(cin, w) for _ in range(n - 1)]
            setattr(self, f"layer{i + 1}", nn.Sequential(*blocks))
        self.out_channels = [width * 2 ** i * block.expansion for i in range(4)]

    def forward(self, x):
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        outs = []
        for i in range(4):
            x = getattr(self, f"layer{i + 1}")(x)
            outs.append(x)
        return outs


class FPN(nn.Module):
    """torchvision FeaturePyramidNetwork (new-style ``inner_blocks.i.0`` names), top-down with
    nearest upsampling; the max-pool extra level is not computed because PARQ never reads it."""

    def __init__(self, in_channels: list, out_channels: int):
        super().__init__()
        self.inner_blocks = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, out_channels, 1)) for c in in_channels)
        self.layer_blocks = nn.ModuleList(
            nn.Sequential(nn.Conv2d(out_channels, out_channels, 3, padding=1))
            for _ in in_channels)

    def forward(self, xs: list) -> list:
        last = self.inner_blocks[-1](xs[-1])
        results = [self.layer_blocks[-1](last)]
        for i in range(len(xs) - 2, -1, -1):
            lateral = self.inner_blocks[i](xs[i])
            last = lateral + F.interpolate(last, size=lateral.shape[-2:], mode="nearest")
            results.insert(0, self.layer_blocks[i](last))
        return results


class ResNetFPN(nn.Module):
    """images (B, 3, H, W), RGB in [0, 1] -> features (B, 4 * fpn_channels, H/4, W/4).

    ImageNet normalisation happens inside, as in the authors' ``ResnetFPN``.
    """

    def __init__(self, depth=50, width=64, fpn_channels=256,
                 pixel_mean=(0.485, 0.456, 0.406), pixel_std=(0.229, 0.224, 0.225)):
        super().__init__()
        self.body = ResNetBody(depth, width)
        self.fpn = FPN(self.body.out_channels, fpn_channels)
        self.register_buffer("pixel_mean", torch.tensor(pixel_mean).reshape(1, 3, 1, 1),
                             persistent=False)
        self.register_buffer("pixel_std", torch.tensor(pixel_std).reshape(1, 3, 1, 1),
                             persistent=False)

    def levels(self, images: torch.Tensor) -> list:
        """(B, 3, H, W) -> the FPN outputs P2..P5, (B, fpn_channels, H / 2^(l+2), W / 2^(l+2))
        (sizes rounded up), before any resizing."""
        return self.fpn(self.body((images - self.pixel_mean) / self.pixel_std))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return concat_levels(self.levels(images))


def concat_levels(levels: list) -> torch.Tensor:
    """P2..P5 -> (B, 4 * F, h, w): each level resized to P2's size (bilinear,
    align_corners=False) and concatenated along channels."""
    size = levels[0].shape[-2:]
    levels = [levels[0]] + [F.interpolate(p, size=size, mode="bilinear", align_corners=False)
                            for p in levels[1:]]
    return torch.cat(levels, dim=1)
