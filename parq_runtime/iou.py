"""3D IoU of upright boxes: bird's-eye polygon intersection times vertical overlap.

As in the authors' (ODAM's) evaluation, boxes are treated as upright: object y along the world
up axis, the footprint a rectangle of extents (size_x, size_z) turned by the box's yaw, the
height size_y.  A predicted rotation is reduced to its yaw.  The footprint intersection is
OpenCV's ``intersectConvexConvex`` (OpenCV is already a runtime dependency).
"""
from __future__ import annotations

import cv2
import numpy as np

from . import geometry


def footprint(center, size, yaw, up=geometry.UP_Z) -> np.ndarray:
    """Bird's-eye rectangle (4, 2) of an upright box, counter-clockwise, in the horizontal
    basis of ``up`` (world x, y for a z-up world)."""
    return _footprint(center, size, yaw, *geometry.horizontal_basis(up))


def _footprint(center, size, yaw, e1, e2) -> np.ndarray:
    c = np.array([np.dot(center, e1), np.dot(center, e2)])
    ax = np.array([np.cos(yaw), np.sin(yaw)]) * size[0] / 2   # object x on the ground
    az = np.array([np.sin(yaw), -np.cos(yaw)]) * size[2] / 2  # object z = x cross up
    return np.stack([c - ax - az, c + ax - az, c + ax + az, c - ax + az])


def vertical_range(center, size, up=geometry.UP_Z) -> tuple:
    return _vertical_range(center, size, geometry.unit(np.asarray(up, dtype=np.float64)))


def _vertical_range(center, size, up_unit) -> tuple:
    h = float(np.dot(center, up_unit))
    return h - size[1] / 2, h + size[1] / 2


def _prepared(boxes, up) -> tuple:
    """Per box, once: vertical ranges (n,), (n,), footprints (n, 4, 2) float32 as
    ``intersectConvexConvex`` takes them, their centres (n, 2), footprint diagonals (n,),
    volumes (n,)."""
    up_unit = geometry.unit(np.asarray(up, dtype=np.float64))
    e1, e2 = geometry.horizontal_basis(up)
    ranges = [_vertical_range(b.center, b.size, up_unit) for b in boxes]
    prints = [_footprint(b.center, b.size, b.yaw, e1, e2) for b in boxes]
    n = len(boxes)
    lo = np.array([r[0] for r in ranges], dtype=np.float64).reshape(n)
    hi = np.array([r[1] for r in ranges], dtype=np.float64).reshape(n)
    middle = np.array([p.mean(0) for p in prints], dtype=np.float64).reshape(n, 2)
    diagonal = np.array([np.hypot(b.size[0], b.size[2]) for b in boxes],
                        dtype=np.float64).reshape(n)
    volume = np.array([float(np.prod(b.size)) for b in boxes], dtype=np.float64).reshape(n)
    return lo, hi, [p.astype(np.float32) for p in prints], middle, diagonal, volume


def iou_upright(a, b, up=geometry.UP_Z) -> float:
    """IoU of two boxes given as objects with ``center``, ``size``, ``yaw``."""
    return float(iou_matrix([a], [b], up)[0, 0])


def iou_matrix(boxes_a: list, boxes_b: list, up=geometry.UP_Z) -> np.ndarray:
    """Pairwise IoU (len(a), len(b)).

    Each box's footprint and height range are computed once, and only the pairs that overlap
    in height and whose footprint centres are closer than their half-diagonals' sum reach the
    polygon intersection.  The scene fusion and the evaluation call this for every snippet;
    with a footprint made for every pair (88% of the time under a profiler), a candidate of
    parq_train.tune's grid took 0.66 s on the 40 validation scenes, and takes 0.27 s now
    (medians of 5); the 700-candidate grid runs in 173 s and chooses the demo's card again
    with the same F1s, and the IoUs are the same bit for bit on 36,019 pairs of the demo's
    detections."""
    out = np.zeros((len(boxes_a), len(boxes_b)))
    if not len(boxes_a) or not len(boxes_b):
        return out
    lo_a, hi_a, print_a, mid_a, diag_a, vol_a = _prepared(boxes_a, up)
    lo_b, hi_b, print_b, mid_b, diag_b, vol_b = _prepared(boxes_b, up)
    height = np.minimum(hi_a[:, None], hi_b[None]) - np.maximum(lo_a[:, None], lo_b[None])
    distance = np.sqrt(np.square(mid_a[:, None] - mid_b[None]).sum(-1))
    near = (height > 0) & (distance <= (diag_a[:, None] + diag_b[None]) / 2)
    for i, j in zip(*np.nonzero(near)):
        area, _ = cv2.intersectConvexConvex(print_a[i], print_b[j])
        if area <= 0:
            continue
        inter = area * height[i, j]
        out[i, j] = float(inter / (vol_a[i] + vol_b[j] - inter))
    return out
