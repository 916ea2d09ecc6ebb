"""Scene-level fusion of per-snippet detections.

Snippets are added in order.  Each snippet's detections are matched to the scene's boxes so far
by the Hungarian algorithm on 3D IoU (scipy's linear_sum_assignment); a pair under IoU 0.1
counts as unmatched, and unmatched detections start new scene boxes.  Classes are not compared.
A scene box is the cluster of the detections matched to it, summarised by ``mode``:

* ``best`` (the ODAM protocol the authors evaluate with): the detection with the highest score;
* ``mean``: the best detection's class, score and rotation, with center and size the
  score-weighted mean over the cluster's detections of that class.  Each snippet sees the
  object from elsewhere, so their errors partly cancel (see below for what it gives).

``min_support``: a scene box is reported only when detections from at least that many
snippets support it; spurious detections rarely recur, real objects seen from several
keyframes do (1, the authors' protocol, reports every box).

On the demo model's 40 validation scenes (2 iterations, 32 queries, each with its best score
threshold and region; ``parq_train.tune``): best/1 F1@0.25 0.360, F1@0.5 0.112; mean/1 0.374,
0.134; mean/2 0.387, 0.162.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from . import geometry
from .errors import ParqError
from .iou import iou_matrix

MATCH_IOU = 0.1
MODES = ("best", "mean")
# The authors' fusion: the best-scoring member stands for its cluster, every cluster kept.
AUTHORS_MODE = "best"
AUTHORS_MIN_SUPPORT = 1


def problems(mode, min_support) -> list:
    """What is wrong with a fusion mode and minimum support (empty when both are valid);
    SceneFusion and the exporter's PARQConfig both check with it."""
    found = []
    if mode not in MODES:
        found.append(f"fusion mode {mode!r} must be one of {', '.join(MODES)}")
    if isinstance(min_support, bool) or not isinstance(min_support, int) or min_support < 1:
        found.append(f"fusion min_support {min_support!r} must be an integer >= 1")
    return found


@dataclass
class _Cluster:
    members: list        # Box, in the order added
    snippets: list       # snippet index of each member
    fused: object = None

    @property
    def best(self) -> int:
        return max(range(len(self.members)), key=lambda i: self.members[i].score)

    @property
    def support(self) -> int:
        """Distinct snippets among the members."""
        return len(set(self.snippets))


@dataclass
class SceneFusion:
    """Accumulates boxes.  ``boxes`` are the scene boxes with enough support, ``sources`` the
    snippet index of each one's best detection, ``supports`` the number of snippets that
    detected each."""

    iou_threshold: float = MATCH_IOU
    up: tuple = geometry.UP_Z
    mode: str = AUTHORS_MODE
    min_support: int = AUTHORS_MIN_SUPPORT
    clusters: list = field(default_factory=list)

    def __post_init__(self):
        found = problems(self.mode, self.min_support)
        if found:
            raise ParqError("; ".join(found))

    def add(self, detections: list, snippet: int = -1) -> list:
        """Fuse one snippet's detections; returns the cluster index each detection went to."""
        if not detections:
            return []
        assigned = [-1] * len(detections)
        if self.clusters:
            iou = iou_matrix(detections, [c.fused for c in self.clusters], self.up)
            rows, cols = linear_sum_assignment(-iou)
            for d, t in zip(rows, cols):
                if iou[d, t] >= self.iou_threshold:
                    assigned[d] = int(t)
        for d, det in enumerate(detections):
            if assigned[d] < 0:
                assigned[d] = len(self.clusters)
                self.clusters.append(_Cluster([], []))
            cluster = self.clusters[assigned[d]]
            cluster.members.append(det)
            cluster.snippets.append(snippet)
            cluster.fused = self._summarise(cluster)
        return assigned

    def _summarise(self, cluster: _Cluster):
        best = cluster.members[cluster.best]
        if self.mode == "best" or len(cluster.members) == 1:
            return best
        same = [b for b in cluster.members if b.label == best.label]
        w = np.array([b.score for b in same])[:, None] / sum(b.score for b in same)
        center = (w * np.stack([b.center for b in same])).sum(0)
        size = (w * np.stack([b.size for b in same])).sum(0)
        return replace(best, center=center, size=size,
                       corners=geometry.box_corners(center, size, best.rotation))

    def _kept(self) -> list:
        return [c for c in self.clusters if c.support >= self.min_support]

    @property
    def boxes(self) -> list:
        return [c.fused for c in self._kept()]

    @property
    def sources(self) -> list:
        return [c.snippets[c.best] for c in self._kept()]

    @property
    def supports(self) -> list:
        """How many snippets detected each of ``boxes``."""
        return [c.support for c in self._kept()]


def fuse(snippet_detections: list, iou_threshold: float = MATCH_IOU, up=geometry.UP_Z,
         mode: str = AUTHORS_MODE, min_support: int = AUTHORS_MIN_SUPPORT) -> SceneFusion:
    fusion = SceneFusion(iou_threshold, tuple(np.asarray(up, dtype=float)), mode, min_support)
    for i, dets in enumerate(snippet_detections):
        fusion.add(dets, i)
    return fusion
