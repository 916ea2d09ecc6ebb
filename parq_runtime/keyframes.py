"""Keyframes and snippets from a video, as the authors form their validation snippets.

A frame becomes a keyframe when its optical axis turned more than ``min_angle`` degrees or its
centre moved more than ``min_distance`` metres since the last keyframe.  Snippets are windows of
``views`` keyframes, ``stride`` keyframes apart (stride = views: non-overlapping, the authors'
validation setting); an incomplete last window is dropped.  A window's views are ``gap``
keyframes apart: 1 (the authors') takes consecutive keyframes; a larger gap widens the baseline
between the views, for a model trained on such snippets.
"""
from __future__ import annotations

import numpy as np

from .errors import ParqError


def select(cam_to_world, min_angle: float = 15.0, min_distance: float = 0.1) -> list:
    """Indices of keyframes among poses (iterable of 4x4 T_world_camera)."""
    if min_angle < 0 or min_distance < 0:
        raise ParqError("keyframe thresholds must not be negative")
    cos_min = np.cos(np.radians(min_angle))
    keep, last = [], None
    for i, T in enumerate(cam_to_world):
        T = np.asarray(T)
        if last is not None:
            cos = float(np.clip(T[:3, 2] @ last[:3, 2], -1.0, 1.0))
            moved = float(np.linalg.norm(T[:3, 3] - last[:3, 3]))
            if not (cos < cos_min or moved > min_distance):
                continue
        keep.append(i)
        last = T
    return keep


def windows(items: list, views: int = 3, stride: int | None = None, gap: int = 1) -> list:
    """Windows of ``views`` items ``gap`` apart (1: consecutive), starting every ``stride``
    items (default: views; with gap 1, non-overlapping)."""
    stride = views if stride is None else stride
    if views < 1 or stride < 1 or gap < 1:
        raise ParqError(f"views ({views}), stride ({stride}) and gap ({gap}) must be at least 1")
    span = span_of(views, gap)
    return [items[s:s + span:gap] for s in range(0, len(items) - span + 1, stride)]


def span_of(views: int, gap: int = 1) -> int:
    """Keyframes a window of ``views`` views ``gap`` apart spans, first to last."""
    return (views - 1) * gap + 1
