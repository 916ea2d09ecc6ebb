"""Mirror augmentation for training (``parq-train --mirror``): each snippet of a batch is, with
probability 1/2, replaced by its mirror image, a room the generator could have made.

It is parq_runtime.mirror (the test-time mirror runs) done in the snippet's local frame. The
local frame is gravity-aligned (y up, z the local view's horizontal forward, x = y x z), so the
mirrored world's local frame is the original's with x negated, and with ``F = diag(-1, 1, 1)``:

    images flipped left-right        cx' = w * s - 1 - cx    (feature pinhole, s = 1 / stride)
    R_local_camera' = F @ R @ F      t_local_camera' = F @ t
    center' = F @ center             R_local_object' = F @ R @ F     size' = size

The feature pinhole's principal point follows from the image's (W - 1 - cx at the network
size) through geometry.scale_camera's c' = (c + 0.5) s - 0.5.  The object frame is reflected
across its y-z plane, which keeps up (y) and front (+z, parq_synth.shapes) where they were, so
a chair's target still points where its backrest does; the box is symmetric under it.

Why: the demo's model is not mirror-consistent (running each snippet mirrored too and fusing
both adds +0.047 F1 at IoU 0.5, docs/demo-experiments.md), and what helped training most was
more rooms (same document, "More scenes, not more steps"): a mirror is one for free.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .data import Snippet

F_FLIP = np.diag([-1.0, 1.0, 1.0]).astype(np.float32)


def mirrored(snippet: Snippet, feature_stride: int) -> Snippet:
    """The mirror image of a training snippet (see the module docstring); the input is kept."""
    width = snippet.images.shape[2]
    camera = snippet.camera.copy()
    camera[:, 2] = width / feature_stride - 1.0 - camera[:, 2]
    T = snippet.T_local_camera.copy()
    T[:, :3, :3] = F_FLIP @ T[:, :3, :3] @ F_FLIP
    T[:, :3, 3] = T[:, :3, 3] * F_FLIP.diagonal()
    return replace(snippet,
                   images=np.ascontiguousarray(snippet.images[:, :, ::-1]),
                   camera=camera, T_local_camera=T,
                   centers=(snippet.centers * F_FLIP.diagonal()).astype(np.float32),
                   rotations=(F_FLIP @ snippet.rotations @ F_FLIP).astype(np.float32),
                   dense_depth=_flip(snippet.dense_depth),
                   dense_labels=_flip(snippet.dense_labels))


def _flip(maps):
    """Per-view maps (N, h, w) flipped left-right with the images; None stays None."""
    return None if maps is None else np.ascontiguousarray(maps[:, :, ::-1])


def mirror_some(snippets: list, rng: np.random.Generator, feature_stride: int) -> list:
    """Each snippet, or with probability 1/2 (drawn from ``rng``) its mirror image."""
    flips = rng.random(len(snippets)) < 0.5
    return [mirrored(s, feature_stride) if flip else s for s, flip in zip(snippets, flips)]
