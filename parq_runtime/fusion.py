"""Scene-level fusion of per-snippet detections (the ODAM protocol the authors evaluate with).

Snippets are added in order.  Each snippet's detections are matched to the scene's boxes so far
by the Hungarian algorithm on 3D IoU (scipy's linear_sum_assignment); a pair under IoU 0.1
counts as unmatched.  A matched scene box is replaced by the detection when the detection's
score is higher; unmatched detections become new scene boxes.  Classes are not compared.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from . import geometry
from .iou import iou_matrix

MATCH_IOU = 0.1


@dataclass
class SceneFusion:
    """Accumulates boxes; ``boxes`` and ``sources`` (snippet index of each box) grow as
    snippets are added."""

    iou_threshold: float = MATCH_IOU
    up: tuple = geometry.UP_Z
    boxes: list = field(default_factory=list)
    sources: list = field(default_factory=list)

    def add(self, detections: list, snippet: int = -1) -> list:
        """Fuse one snippet's detections; returns the scene index each detection went to."""
        if not detections:
            return []
        assigned = [-1] * len(detections)
        if self.boxes:
            iou = iou_matrix(detections, self.boxes, self.up)
            rows, cols = linear_sum_assignment(-iou)
            for d, t in zip(rows, cols):
                if iou[d, t] < self.iou_threshold:
                    continue
                assigned[d] = int(t)
                if detections[d].score > self.boxes[t].score:
                    self.boxes[t] = detections[d]
                    self.sources[t] = snippet
        for d, det in enumerate(detections):
            if assigned[d] < 0:
                assigned[d] = len(self.boxes)
                self.boxes.append(det)
                self.sources.append(snippet)
        return assigned


def fuse(snippet_detections: list, iou_threshold: float = MATCH_IOU,
         up=geometry.UP_Z) -> SceneFusion:
    fusion = SceneFusion(iou_threshold, tuple(np.asarray(up, dtype=float)))
    for i, dets in enumerate(snippet_detections):
        fusion.add(dets, i)
    return fusion
