"""From the last iteration's box parameters to detections, as the authors' evaluation does.

score, label = max, argmax of the softmax over all classes + no-object; no-object is dropped.
Class-agnostic NMS (IoU 0.1) runs on the axis-aligned bounds of the rotated corners in the
local frame over every box that is not no-object; then boxes whose local center lies outside
the evaluation region (x in (-1.5, 1.5), z in (0, 2) m for the release) or whose score is not
above the threshold are removed.  NMS running before the region and score filters is the
authors' order: a box outside the region can suppress one inside it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry


@dataclass
class Box:
    """One detection in the world frame.

    center (3,) metres; size (3,) full extents along the object's x, y (up), z axes;
    rotation (3, 3) = R_world_object; yaw radians about the up axis (see geometry.yaw);
    corners (8, 3) in geometry.CORNER_SIGNS order; query: index of the query it came from;
    viewpoint (3,) world position of the camera it was seen from (its snippet frame's
    origin, the middle view's camera), which ``ray`` fusion needs; None when unknown."""

    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    yaw: float
    label: int
    class_name: str
    score: float
    corners: np.ndarray
    query: int = -1
    viewpoint: np.ndarray | None = None

    def to_json(self) -> dict:
        return {"class": self.class_name, "label": int(self.label),
                "score": round(float(self.score), 6),
                "center": np.round(self.center, 6).tolist(),
                "size": np.round(self.size, 6).tolist(),
                "rotation": np.round(self.rotation, 6).tolist(),
                "yaw": round(float(self.yaw), 6),
                "corners": np.round(self.corners, 6).tolist()}

    @classmethod
    def from_json(cls, d: dict, classes=None) -> "Box":
        center = np.asarray(d["center"], dtype=np.float64)
        size = np.asarray(d["size"], dtype=np.float64)
        rotation = np.asarray(d["rotation"], dtype=np.float64)
        label = int(d["label"]) if "label" in d else list(classes).index(d["class"])
        return cls(center, size, rotation, float(d.get("yaw", geometry.yaw(rotation))), label,
                   d.get("class", str(label)), float(d.get("score", 1.0)),
                   geometry.box_corners(center, size, rotation))


def softmax(logits: np.ndarray) -> np.ndarray:
    z = logits - logits.max(-1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(-1, keepdims=True)


def nms_axis_aligned(corners: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Greedy NMS on axis-aligned bounds of corners (M, 8, 3); returns kept indices, best first.
    A box is suppressed when its IoU with a kept one is above ``iou``."""
    lo = corners.min(1)
    hi = corners.max(1)
    volume = np.prod(hi - lo, -1)
    order = np.argsort(-scores, kind="stable")
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        inter = np.prod(np.clip(np.minimum(hi[i], hi[rest]) - np.maximum(lo[i], lo[rest]),
                                0, None), -1)
        overlap = inter / (volume[i] + volume[rest] - inter)
        order = rest[~(overlap > iou)]
    return np.asarray(keep, dtype=np.int64)


def detections(last, T_world_local: np.ndarray, classes: list, score_threshold: float,
               nms_iou: float, region=None, up=geometry.UP_Z) -> list:
    """Boxes (world frame) from the last :class:`~parq_runtime.loop.Iteration`, best first.

    region: (xmin, xmax, zmin, zmax) of kept local centers, or None to keep all."""
    prob = softmax(np.asarray(last.logits, dtype=np.float64))
    scores = prob.max(-1)
    labels = prob.argmax(-1)
    center = np.asarray(last.center, dtype=np.float64)
    size = np.asarray(last.size, dtype=np.float64)
    R_local_object = geometry.rotation_from_6d(last.ortho6d)
    corners_local = geometry.box_corners(center, size, R_local_object)
    candidates = np.flatnonzero(labels != len(classes))
    kept = candidates[nms_axis_aligned(corners_local[candidates], scores[candidates], nms_iou)]
    keep = scores[kept] > score_threshold
    if region is not None:
        x, z = center[kept, 0], center[kept, 2]
        keep &= (x > region[0]) & (x < region[1]) & (z > region[2]) & (z < region[3])
    out = []
    for q in kept[keep]:
        R_world_object = T_world_local[:3, :3] @ R_local_object[q]
        center_world = geometry.transform(T_world_local, center[q])
        out.append(Box(center_world, size[q], R_world_object,
                       float(geometry.yaw(R_world_object, up)), int(labels[q]),
                       classes[labels[q]], float(scores[q]),
                       geometry.box_corners(center_world, size[q], R_world_object), int(q),
                       T_world_local[:3, 3].astype(np.float64)))
    return out
