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
    e1, e2 = geometry.horizontal_basis(up)
    c = np.array([np.dot(center, e1), np.dot(center, e2)])
    ax = np.array([np.cos(yaw), np.sin(yaw)]) * size[0] / 2   # object x on the ground
    az = np.array([np.sin(yaw), -np.cos(yaw)]) * size[2] / 2  # object z = x cross up
    return np.stack([c - ax - az, c + ax - az, c + ax + az, c - ax + az])


def vertical_range(center, size, up=geometry.UP_Z) -> tuple:
    h = float(np.dot(center, geometry.unit(np.asarray(up, dtype=np.float64))))
    return h - size[1] / 2, h + size[1] / 2


def iou_upright(a, b, up=geometry.UP_Z) -> float:
    """IoU of two boxes given as objects with ``center``, ``size``, ``yaw``."""
    lo_a, hi_a = vertical_range(a.center, a.size, up)
    lo_b, hi_b = vertical_range(b.center, b.size, up)
    height = min(hi_a, hi_b) - max(lo_a, lo_b)
    if height <= 0:
        return 0.0
    pa = footprint(a.center, a.size, a.yaw, up)
    pb = footprint(b.center, b.size, b.yaw, up)
    reach = (np.hypot(a.size[0], a.size[2]) + np.hypot(b.size[0], b.size[2])) / 2
    if np.linalg.norm(pa.mean(0) - pb.mean(0)) > reach:
        return 0.0
    area, _ = cv2.intersectConvexConvex(pa.astype(np.float32), pb.astype(np.float32))
    if area <= 0:
        return 0.0
    inter = area * height
    vol_a = float(np.prod(a.size))
    vol_b = float(np.prod(b.size))
    return float(inter / (vol_a + vol_b - inter))


def iou_matrix(boxes_a: list, boxes_b: list, up=geometry.UP_Z) -> np.ndarray:
    """Pairwise IoU (len(a), len(b))."""
    out = np.zeros((len(boxes_a), len(boxes_b)))
    for i, a in enumerate(boxes_a):
        for j, b in enumerate(boxes_b):
            out[i, j] = iou_upright(a, b, up)
    return out
