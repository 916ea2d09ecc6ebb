"""The auxiliary dense loss (``parq-train --dense-weight``): beyond the paper's objective.

Backbone pretraining (:mod:`parq_train.pretrain`) teaches the ResNet-FPN, per feature cell
(stride 4), the scene depth and which class of object (or the room) is seen there.  PARQ's
objective then trains it on a few boxes per snippet, and nothing keeps that dense knowledge.
With a weight above 0, training keeps asking for it: a linear head (a 1x1 convolution, thrown
away after training like the pretraining's) reads the features of every view of every snippet
the PARQ step has already computed, and its loss (L1 on log-depth + cross entropy on the class
of each cell, as in pretraining) is added to the paper's objective times the weight.  A 1x1
head rather than the pretraining's 3x3 one: on 12 images of 40 x 30 cells and 128 channels a
3x3 convolution would cost about as much as the whole ResNet, a 1x1 one nothing measurable.

Why: the demo's misses are mostly objects that no scene box comes near, and most of them are
small (trash bins, displays, "other"); whether dense supervision during training keeps the
features that find them is the experiment (docs/demo-experiments.md).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def class_lookup(boxes: list, num_classes: int) -> np.ndarray:
    """Instance-mask value -> class label: 0 (the room) -> ``num_classes``, 1 + j -> boxes[j]'s
    label (parq-synth's instance/<i>.png)."""
    return np.array([num_classes] + [b["label"] for b in boxes], dtype=np.int64)


def dense_targets(depth: np.ndarray, mask: np.ndarray, lut: np.ndarray, feature_size) -> tuple:
    """One frame's depth (H, W) metres (0: none) and instance mask (H, W) -> log-depth (h, w)
    (NaN where there is no depth) and labels (h, w) through ``lut`` (:func:`class_lookup`),
    sampled at the centre of each feature cell; feature_size = (w, h)."""
    h, w = depth.shape
    fw, fh = feature_size
    ys = np.clip(((np.arange(fh) + 0.5) * h / fh).astype(int), 0, h - 1)
    xs = np.clip(((np.arange(fw) + 0.5) * w / fw).astype(int), 0, w - 1)
    d = depth[np.ix_(ys, xs)]
    log_depth = np.where(d > 0, np.log(np.maximum(d, 1e-3)), np.nan)
    return log_depth, lut[np.clip(mask[np.ix_(ys, xs)], 0, len(lut) - 1)]



class DenseProbe(nn.Module):
    """features (B, C, h, w) -> log-depth (B, h, w) and class logits (B, classes + 1, h, w),
    a 1x1 convolution; the last class is the room (no object)."""

    def __init__(self, dim: int, num_classes: int):
        super().__init__()
        self.conv = nn.Conv2d(dim, 2 + num_classes, 1)

    def forward(self, features):
        out = self.conv(features)
        return out[:, 0], out[:, 1:]


def dense_loss(probe: DenseProbe, features: torch.Tensor, log_depth: torch.Tensor,
               labels: torch.Tensor) -> tuple:
    """(loss, parts) for features (B, C, h, w) against log_depth (B, h, w) (NaN: none) and
    labels (B, h, w): mean L1 on log-depth over cells with depth + cross entropy."""
    predicted_depth, logits = probe(features)
    valid = torch.isfinite(log_depth)
    depth = (predicted_depth[valid] - log_depth[valid]).abs().mean()
    label = F.cross_entropy(logits, labels)
    return depth + label, {"dense depth": float(depth.detach()),
                           "dense class": float(label.detach())}
