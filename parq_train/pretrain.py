"""Backbone pretraining on dense targets: the stand-in for the ImageNet weights the authors
start from, which cannot be downloaded here.

The ResNet-FPN learns, per feature pixel (stride 4), the scene depth and which class of object
(or room) is seen there, from the generated scenes' depth maps and instance masks.  A small
dense head (3x3 conv, ReLU, 1x1 conv) reads the concatenated FPN features; it is used only
here and thrown away.  PARQ itself is then trained with the paper's objective alone.
"""
from __future__ import annotations

import json
import pathlib
import time

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from parq_runtime import keyframes, preprocess
from parq_runtime.readers import open_capture

from .dense import class_lookup, dense_targets
from .progress import minutes


class DenseHead(nn.Module):
    """features (B, C, h, w) -> log-depth (B, h, w) and class logits (B, classes + 1, h, w);
    the last class is the room (no object)."""

    def __init__(self, dim: int, num_classes: int):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(dim, dim, 3, padding=1), nn.ReLU(),
                                 nn.Conv2d(dim, 2 + num_classes, 1))

    def forward(self, features):
        out = self.net(features)
        return out[:, 0], out[:, 1:]


def frame_targets(folder, config, stride: int = 4) -> tuple:
    """Keyframes of one scene: images (F, h, w, 3) uint8 at the network size, log-depth
    (F, h/4, w/4) (NaN where there is no depth) and labels (F, h/4, w/4), sampled at the
    centre of each 4x4 block."""
    folder = pathlib.Path(folder)
    capture = open_capture(folder, "scannet")
    boxes = json.loads((folder / "boxes.json").read_text())["boxes"]
    lut = class_lookup(boxes, len(config.classes))
    images, depths, labels = [], [], []
    for i in keyframes.select([f.cam_to_world for f in capture.frames]):
        f = capture.frames[i]
        image, _ = preprocess.prepare(f.load_image(), f.intrinsics, config.image_size,
                                      config.image_filter)
        depth = np.asarray(Image.open(folder / "depth" / f"{f.name}.png"), np.float64) / 1000
        mask = np.asarray(Image.open(folder / "instance" / f"{f.name}.png"), np.int64)
        log_depth, label = dense_targets(depth, mask, lut, config.feature_size)
        images.append(image)
        depths.append(log_depth)
        labels.append(label)
    return np.stack(images), np.stack(depths).astype(np.float32), np.stack(labels)


def pretrain(backbone: nn.Module, config, folders: list, steps: int, seed: int,
             batch: int = 12, lr: float = 1e-3, log=print, log_every: int = 100) -> list:
    """Train ``backbone`` (ResNetFPN, trainable norms) in place; returns the loss history."""
    data = [frame_targets(f, config) for f in folders]
    images = np.concatenate([d[0] for d in data])
    depths = np.concatenate([d[1] for d in data])
    labels = np.concatenate([d[2] for d in data])
    log(f"pretraining on {len(images)} keyframes of {len(folders)} scenes")
    rng = np.random.default_rng(seed)
    head = DenseHead(config.feature_dim, len(config.classes))
    params = list(backbone.parameters()) + list(head.parameters())
    optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    backbone.train()
    history, running, start = [], {"depth": 0.0, "class": 0.0}, time.perf_counter()
    for step in range(steps):
        for group in optimizer.param_groups:
            group["lr"] = lr * min(1.0, (step + 1) / 200) * 0.5 * (1 + np.cos(np.pi * step / steps))
        idx = rng.integers(0, len(images), batch)
        x = torch.from_numpy(images[idx]).permute(0, 3, 1, 2).float() / 255.0
        gain = torch.from_numpy(rng.uniform(0.75, 1.25, (batch, 1, 1, 1))).float()
        x = (x * gain).clamp(0, 1)
        log_depth, logits = head(backbone(x))
        target_depth = torch.from_numpy(depths[idx])
        valid = torch.isfinite(target_depth)
        depth_loss = (log_depth[valid] - target_depth[valid]).abs().mean()
        class_loss = F.cross_entropy(logits, torch.from_numpy(labels[idx]))
        loss = depth_loss + class_loss
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        running["depth"] += float(depth_loss.detach())
        running["class"] += float(class_loss.detach())
        if (step + 1) % log_every == 0 or step + 1 == steps:
            mean = {k: v / log_every for k, v in running.items()}
            history.append({"step": step + 1, **mean})
            elapsed = time.perf_counter() - start
            log(f"pretrain step {step + 1}/{steps}  {minutes(elapsed, step + 1, steps)}  "
                f"depth {mean['depth']:.3f}  class {mean['class']:.3f}")
            running = {k: 0.0 for k in running}
    return history


PRETRAINED_FORMAT = "parq-train pretrained backbone"


def record_of(config, steps: int, seed: int, data_seed: int, folders: list, frames: int,
              **more) -> dict:
    """What :func:`save_backbone` stores beside the weights: how the pretraining was made
    (steps, seed, the scenes' generator seed, count and frames, the image size), plus ``more``."""
    return {"steps": steps, "seed": seed,
            "data": {"seed": data_seed, "scenes": len(folders), "frames": frames},
            "image_size": list(config.image_size), **more}


def save_backbone(path, backbone: nn.Module, record: dict) -> None:
    """Write a pretrained ResNet-FPN (trainable norms, as :func:`pretrain` leaves it) with
    ``record`` (:func:`record_of`), for ``parq-train --pretrained``.
    Tensors and plain values only, so :func:`read_backbone` reads it without unpickling code."""
    path = pathlib.Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": PRETRAINED_FORMAT, "pretraining": record,
                "backbone": backbone.state_dict()}, tmp)
    tmp.replace(path)


def read_backbone(path, config) -> tuple:
    """(state dict, record) of a file of :func:`save_backbone`, checked before any work is
    spent: ParqError, naming the file, for a missing or foreign file or one pretrained at
    another image size than ``config``'s.  Read with ``weights_only``: no code is unpickled."""
    from parq_runtime.errors import ParqError

    path = pathlib.Path(path)
    if not path.is_file():
        raise ParqError(f"{path}: no such pretrained backbone file")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for files it cannot read
        raise ParqError(f"{path}: not a readable torch file ({type(e).__name__})") from None
    if not isinstance(saved, dict) or saved.get("format") != PRETRAINED_FORMAT:
        raise ParqError(f"{path}: not a pretrained backbone written by parq-train")
    record = saved["pretraining"]
    if list(record.get("image_size", ())) != list(config.image_size):
        raise ParqError(f"{path}: pretrained at image size {record.get('image_size')}, "
                        f"this model takes {list(config.image_size)}")
    return saved["backbone"], record


def set_backbone(backbone: nn.Module, state: dict, path) -> None:
    """Load ``state`` (from :func:`read_backbone` of ``path``) into ``backbone``; ParqError
    naming the file when it was made for another ResNet depth or width."""
    from parq_runtime.errors import ParqError

    try:
        backbone.load_state_dict(state)
    except RuntimeError as e:
        lines = [line.strip() for line in str(e).strip().splitlines() if line.strip()]
        raise ParqError(f"{path}: made for another backbone ({lines[-1]})") from None
