"""Scene-level fusion of per-snippet detections.

Snippets are added in order.  Each snippet's detections are matched to the scene's boxes so far
by the Hungarian algorithm on 3D IoU (scipy's linear_sum_assignment); a pair under the
matching IoU (``iou_threshold``, the model card's ``match_iou``; the authors' 0.1) counts as
unmatched, and unmatched detections start new scene boxes.  Classes are not compared.  A lower
floor lets two snippets' detections of one small object join although their depth errors
leave them barely overlapping, which adds to the support they need to be reported (the
demo's card: 0.01, +0.009 at IoU 0.25 on validation and held out; docs/demo-experiments.md,
"The fusion's matching IoU, chosen by the tuning").

A scene box is the cluster of the detections matched to it, summarised by ``mode``:

* ``best`` (the ODAM protocol the authors evaluate with): the detection with the highest score;
* ``mean``: the best detection's class, score and rotation, with center and size the
  score-weighted mean over the cluster's detections of that class.  Each snippet sees the
  object from elsewhere, so their errors partly cancel (see below for what it gives).  Sizes
  are averaged in the best detection's axes: a detection turned by more than 45 degrees from
  it (about the up axis, modulo 180) is the same box with its two horizontal extents swapped
  (``aligned_size``).  On the demo's 120 held-out scenes 64% of the kept scene boxes have
  detections so turned (21% of their detections); averaging their extents unswapped made
  long boxes squarer, and aligning them gained F1@0.25 +0.017 (+0.008 to +0.027, paired)
  (docs/demo-experiments.md, "Sizes averaged in one box's axes").
* ``ray``: as ``mean``, but the center is the weighted least-squares point of the
  detections' centers, each trusted ``ray_ratio`` times less along its viewing ray (from its
  snippet's camera, ``Box.viewpoint``) than across it: information matrix
  ``score * ((I - r r^T) + r r^T / ray_ratio)`` for the unit ray ``r``.  A snippet's three
  views are close together, so a detection's depth along the ray is its least certain part
  (on the demo's held-out scenes, median error 0.186 m along the ray and 0.079 m across it,
  docs/demo-experiments.md); snippets that see the object from other directions pin that depth down, as in
  triangulation.  ``ray_ratio`` 1 is ``mean``; a box with no viewpoint counts isotropically.

``scene_nms``: scene boxes of one class that overlap by more than this IoU are taken for one
object, and only the best-scoring is reported (None: off, as in the authors' protocol).  The
matching above joins a detection to at most one scene box, so two clusters can grow on one
object (each snippet's detection goes to one of them); on the demo's 120 held-out scenes 51 of
the 564 boxes its card kept were such second boxes, and NMS at IoU 0.05 after the support filter
removed all of them: F1@0.25 +0.019 (+0.008 to +0.029, paired), F1@0.5 -0.004 (-0.014 to
+0.005), through parq-run's pipeline as through the saved detections; the demo's card carries
it (docs/demo-experiments.md, "Scene NMS").

``floor``: with ``floor_height`` set (the floor's height along ``up``, world metres; found in the
images by parq_runtime.floor) the reported box of a class in ``floor_classes`` gets one more
term in the ``ray`` solve: its center's height is pulled to ``floor_height`` plus half the
box's height with weight ``floor_weight`` (the detections' weights sum to 1, and each counts 1
across its ray).  The viewing rays point down at furniture, so that height fixes much of the
depth along them.  It changes only the reported boxes, after the support filter and scene NMS;
the matching sees the boxes without it.  On the demo's 120 held-out scenes, with the floor
found in 100 of them: F1@0.25 +0.037 (+0.023 to +0.051, paired), F1@0.5 +0.020
(docs/demo-experiments.md, "The floor, found in the images").

``labels``: which class a scene box reports.  ``best`` (the authors'): its best-scoring
detection's.  ``vote``: the class whose detections' scores sum highest over the cluster (ties:
the one with the single best score), with the best-scoring detection of that class standing
for the box.  The matching does not compare classes, so one object's cluster holds detections
that call it different things (a bin and an "other", a cabinet and a bookshelf), and one
confident wrong call outvoted several right ones.  On the demo's 160 validation scenes, with
its card otherwise unchanged, ``vote`` scored F1@0.25 +0.007 (+0.000 to +0.014, paired, ahead
in 95% of the resamples) and F1@0.5 +0.010 (+0.003 to +0.017, 99%); summing class
probabilities instead of the argmax scores gave the same (+0.006 / +0.009).  Chosen there by
parq_train.tune, on the 120 held-out scenes it scores +0.007 (-0.003 to +0.016) and +0.009
(+0.001 to +0.018) (docs/demo-experiments.md, "Scene boxes labelled by a vote").

``min_support``: a scene box is reported only when detections from at least that many
snippets support it; spurious detections rarely recur, real objects seen from several
keyframes do (1, the authors' protocol, reports every box).  With mirror runs (``parq-run
--mirror``, the demo card's default) each snippet is also run on its mirror image
(parq_runtime.mirror), and support counts runs: an object two snippets detect both ways has
support 4.

On the demo model's 40 validation scenes (2 iterations, 32 queries, each with its best score
threshold and region; ``parq_train.tune``), for the demo before the current one: best/1
F1@0.25 0.360, F1@0.5 0.112; mean/1 0.374, 0.134; mean/2 0.387, 0.162.  For the current demo
at its card's threshold and region: mean/2 0.494 / 0.274, ray/2 (ratio 5) 0.534 / 0.344,
(ratio 10) 0.534 / 0.339; on the held-out scenes mean/2 0.436 / 0.197, ray/2 0.461 / 0.226
(ratio 5) and 0.482 / 0.274 (ratio 10).  Chosen again on 160 validation scenes for the
demo's run setting (2 iterations x 64 queries), the ratio is 30: 0.489 / 0.307 on 120 held-out
scenes (docs/demo-model.md); with mirror runs, the card's run setting since, support 4 runs: 0.504 / 0.354;
with scene NMS 0.05 after that: 0.523 / 0.349; with sizes averaged in one box's axes
(``aligned_size``), 0.540 / 0.356; with the floor prior (scene NMS 0.1, five floor classes at
weight 3), 0.577 / 0.375; with labels by vote, 0.583 / 0.385; for the current weights, with a
matching IoU of 0.01 (the current card), 0.592 / 0.389 on 240 held-out scenes against 0.583 /
0.384 at the authors' 0.1.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from . import geometry
from .errors import ParqError
from .iou import iou_matrix

MATCH_IOU = 0.1
FLOOR_WEIGHT = 3.0   # the floor term's weight against the detections' (which sum to 1)
MODES = ("best", "mean", "ray")
LABEL_RULES = ("best", "vote")   # which class a scene box reports (module doc, ``labels``)
SCENE_NMS_OFF = "off"  # a run setting's word for no scene NMS, whatever the card says
FLOOR_OFF = "off"      # a run setting's word for no floor prior, whatever the card says
RAY_RATIO = 10.0     # along-ray / across-ray variance of a detection's center, ``ray`` mode
# The authors' fusion: the best-scoring member stands for its cluster, every cluster kept.
AUTHORS_MODE = "best"
AUTHORS_MIN_SUPPORT = 1
AUTHORS_LABELS = "best"


def problems(mode, min_support, ray_ratio=RAY_RATIO, scene_nms=None, floor_classes=(),
             floor_weight=FLOOR_WEIGHT, classes=None, labels=AUTHORS_LABELS,
             match_iou=MATCH_IOU) -> list:
    """What is wrong with a fusion mode, minimum support, ray ratio, scene NMS IoU, floor
    prior, label rule and matching IoU (empty when all are valid); ``classes``: the model's,
    which the floor classes must be among (None: not checked).  SceneFusion, the model card and
    the exporter's PARQConfig all check with it."""
    found = []
    if isinstance(match_iou, bool) or not isinstance(match_iou, (int, float)) \
            or not 0.0 < match_iou <= 1.0:
        found.append(f"fusion match_iou {match_iou!r} must be an IoU in (0, 1]")
    if labels not in LABEL_RULES:
        found.append(f"fusion labels {labels!r} must be one of {', '.join(LABEL_RULES)}")
    if not isinstance(floor_classes, (list, tuple)) or not all(
            isinstance(c, str) for c in floor_classes):
        found.append(f"fusion floor_classes {floor_classes!r} must be a list of class names")
    elif floor_classes and mode != "ray":
        found.append(f"fusion floor_classes need the ray mode, not {mode!r}")
    elif classes is not None and any(c not in classes for c in floor_classes):
        found.append(f"fusion floor_classes {[c for c in floor_classes if c not in classes]} "
                     "are not among the model's classes")
    if isinstance(floor_weight, bool) or not isinstance(floor_weight, (int, float)) \
            or not 0.0 < floor_weight < float("inf"):
        found.append(f"fusion floor_weight {floor_weight!r} must be a number > 0")
    if scene_nms is not None and (isinstance(scene_nms, bool)
                                  or not isinstance(scene_nms, (int, float))
                                  or not 0.0 <= scene_nms < 1.0):
        found.append(f"fusion scene_nms {scene_nms!r} must be null (off) or an IoU in [0, 1)")
    if mode not in MODES:
        found.append(f"fusion mode {mode!r} must be one of {', '.join(MODES)}")
    if isinstance(min_support, bool) or not isinstance(min_support, int) or min_support < 1:
        found.append(f"fusion min_support {min_support!r} must be an integer >= 1")
    if isinstance(ray_ratio, bool) or not isinstance(ray_ratio, (int, float)) \
            or not 1.0 <= ray_ratio < float("inf"):
        found.append(f"fusion ray_ratio {ray_ratio!r} must be a number >= 1 (along-ray over "
                     "across-ray variance; 1 is the mean)")
    return found


@dataclass
class _Cluster:
    members: list        # Box, in the order added
    runs: list           # (snippet index, mirrored, sampling phase) of each member
    fused: object = None

    @property
    def best(self) -> int:
        return max(range(len(self.members)), key=lambda i: self.members[i].score)

    def lead(self, labels: str) -> int:
        """The member that stands for the cluster under the label rule ``labels`` (module
        doc): the best-scoring one, or the best-scoring one of the class that wins the vote
        (score sums; ties to the class with the single best score)."""
        if labels == AUTHORS_LABELS:
            return self.best
        votes = {}
        for i, box in enumerate(self.members):
            total, top = votes.get(box.label, (0.0, -1))
            if top < 0 or box.score > self.members[top].score:
                top = i
            votes[box.label] = (total + box.score, top)
        return max(votes.values(), key=lambda v: (v[0], self.members[v[1]].score))[1]

    @property
    def support(self) -> int:
        """Distinct runs among the members: snippets, each counted twice when it was also run
        mirrored (parq_runtime.mirror) and both runs detected the object, and again for each
        other sampling phase it was run at (parq_runtime.preprocess.PHASES)."""
        return len(set(self.runs))


@dataclass
class SceneFusion:
    """Accumulates boxes.  ``boxes`` are the scene boxes with enough support, ``sources`` the
    snippet index of the detection that stands for each (the best one, or the best of the
    voted class: ``labels``), ``supports`` the number of snippets that
    detected each (with mirror-image runs: the runs, _Cluster.support)."""

    iou_threshold: float = MATCH_IOU
    up: tuple = geometry.UP_Z
    mode: str = AUTHORS_MODE
    min_support: int = AUTHORS_MIN_SUPPORT
    ray_ratio: float = RAY_RATIO
    scene_nms: float | None = None
    floor_classes: tuple = ()
    floor_weight: float = FLOOR_WEIGHT
    floor_height: float | None = None     # set once known; None: no box is pulled to a floor
    labels: str = AUTHORS_LABELS
    clusters: list = field(default_factory=list)

    def __post_init__(self):
        found = problems(self.mode, self.min_support, self.ray_ratio, self.scene_nms,
                         self.floor_classes, self.floor_weight, labels=self.labels,
                         match_iou=self.iou_threshold)
        if found:
            raise ParqError("; ".join(found))

    def add(self, detections: list, snippet: int = -1, mirrored: bool = False,
            phase: float = 0.0) -> list:
        """Fuse one snippet's detections (``mirrored``: from its mirror-image run, reflected
        back; ``phase``: the frames' point-sampling grid of the run); returns the cluster
        index each detection went to."""
        if not detections:
            return []
        assigned = self._match(detections)
        for d, det in enumerate(detections):
            if assigned[d] < 0:
                assigned[d] = len(self.clusters)
                self.clusters.append(_Cluster([], []))
            cluster = self.clusters[assigned[d]]
            cluster.members.append(det)
            cluster.runs.append((snippet, bool(mirrored), float(phase)))
            cluster.fused = self._summarise(cluster)
        return assigned

    def _match(self, detections: list) -> list:
        """The scene box (cluster index) each detection joins, -1 for none: the Hungarian
        assignment on 3D IoU, pairs under ``iou_threshold`` left unmatched."""
        assigned = [-1] * len(detections)
        if self.clusters:
            iou = iou_matrix(detections, [c.fused for c in self.clusters], self.up)
            rows, cols = linear_sum_assignment(-iou)
            for d, t in zip(rows, cols):
                if iou[d, t] >= self.iou_threshold:
                    assigned[d] = int(t)
        return assigned

    def _summarise(self, cluster: _Cluster, floor: float | None = None):
        """The cluster's box; with ``floor`` (a height along ``up``) its center's height is
        also pulled to the floor plus half its height (the class decides: _reported)."""
        best = cluster.members[cluster.lead(self.labels)]
        if floor is None and (self.mode == "best" or len(cluster.members) == 1):
            return best
        same = [b for b in cluster.members if b.label == best.label]
        w = np.array([b.score for b in same])[:, None] / sum(b.score for b in same)
        center = (w * np.stack([b.center for b in same])).sum(0)
        size = (w * np.stack([aligned_size(b, best) for b in same])).sum(0)
        if self.mode == "ray" and (len(same) > 1 or floor is not None):
            standing = None if floor is None else (np.asarray(self.up, dtype=np.float64),
                                                   floor + size[1] / 2, self.floor_weight)
            center = ray_center(same, w[:, 0], self.ray_ratio, standing)
        return replace(best, center=center, size=size,
                       corners=geometry.box_corners(center, size, best.rotation))

    def _reported(self, cluster: _Cluster):
        """What a kept cluster reports: its box, pulled to the floor when one is known and
        its class stands on it."""
        if self.floor_height is None or cluster.fused.class_name not in self.floor_classes:
            return cluster.fused
        return self._summarise(cluster, self.floor_height)

    def floor_guess(self) -> float | None:
        """A coarse floor height along ``up``: the median bottom of the reported boxes of the
        floor classes, before any floor pull (None: there are none).  It picks which of the
        images' floor-like planes is the floor (parq_runtime.floor.choose)."""
        up = np.asarray(self.up, dtype=np.float64)
        bottoms = [c.fused.center @ up - c.fused.size[1] / 2 for c in self._kept()
                   if c.fused.class_name in self.floor_classes]
        return float(np.median(bottoms)) if bottoms else None

    def _kept(self, min_support: int | None = None) -> list:
        """The clusters with at least ``min_support`` (None: this fusion's) runs, less those
        that ``scene_nms`` takes for a second box on an object (in the order added)."""
        least = self.min_support if min_support is None else min_support
        kept = [c for c in self.clusters if c.support >= least]
        if self.scene_nms is None or len(kept) < 2:
            return kept
        boxes = [c.fused for c in kept]
        overlap = iou_matrix(boxes, boxes, self.up)
        chosen = []
        for i in sorted(range(len(kept)), key=lambda i: -boxes[i].score):
            if not any(boxes[j].class_name == boxes[i].class_name
                       and overlap[i, j] > self.scene_nms for j in chosen):
                chosen.append(i)
        return [kept[i] for i in sorted(chosen)]

    @property
    def boxes(self) -> list:
        return [self._reported(c) for c in self._kept()]

    def boxes_with_support(self, min_support: int) -> list:
        """The scene boxes that ``min_support`` would keep: the clusters do not depend on it
        (it only filters them), so one fusion answers for every support (parq_train.tune)."""
        return [self._reported(c) for c in self._kept(min_support)]

    @property
    def sources(self) -> list:
        return [c.runs[c.lead(self.labels)][0] for c in self._kept()]

    @property
    def supports(self) -> list:
        """How many runs detected each of ``boxes``: snippets, and their mirror-image runs
        when there were any (_Cluster.support)."""
        return [c.support for c in self._kept()]


def aligned_size(box, reference) -> np.ndarray:
    """(3,) ``box``'s size along ``reference``'s axes (x, up, z): swapped x and z extents when
    the two boxes' yaws differ by more than 45 degrees modulo 180, since a box turned by 90
    degrees with its horizontal extents swapped is the same box."""
    turn = (box.yaw - reference.yaw + np.pi / 2) % np.pi - np.pi / 2    # in [-pi/2, pi/2)
    size = np.asarray(box.size, dtype=np.float64)
    return size[[2, 1, 0]] if abs(turn) > np.pi / 4 else size


def ray_center(boxes: list, weights: np.ndarray, ray_ratio: float,
               standing: tuple | None = None) -> np.ndarray:
    """(3,) world point minimising sum_i (x - c_i)^T A_i (x - c_i), A_i = w_i ((I - r_i r_i^T)
    + r_i r_i^T / ray_ratio), with c_i a box's center and r_i the unit ray from its viewpoint
    to it (A_i = w_i I for a box without one, or seen from its own center); ``standing`` =
    (up, height, weight) adds weight (up . x - height)^2: the center's height on a floor."""
    A_sum, b_sum = np.zeros((3, 3)), np.zeros(3)
    for box, w in zip(boxes, weights):
        A = np.eye(3)
        if box.viewpoint is not None:
            ray = np.asarray(box.center, dtype=np.float64) - box.viewpoint
            length = np.linalg.norm(ray)
            if length > 1e-9:
                r = ray / length
                A = A - (1.0 - 1.0 / ray_ratio) * np.outer(r, r)
        A_sum += w * A
        b_sum += w * (A @ box.center)
    if standing is not None:
        up, height, weight = standing
        A_sum += weight * np.outer(up, up)
        b_sum += weight * height * up
    # A_sum is positive definite: every A_i has eigenvalues 1 and 1 / ray_ratio > 0, and the
    # floor term is positive semi-definite
    return np.linalg.solve(A_sum, b_sum)


def fuse(snippet_detections: list, iou_threshold: float = MATCH_IOU, up=geometry.UP_Z,
         mode: str = AUTHORS_MODE, min_support: int = AUTHORS_MIN_SUPPORT,
         ray_ratio: float = RAY_RATIO, scene_nms: float | None = None) -> SceneFusion:
    fusion = SceneFusion(iou_threshold, tuple(np.asarray(up, dtype=float)), mode, min_support,
                         ray_ratio, scene_nms)
    for i, dets in enumerate(snippet_detections):
        fusion.add(dets, i)
    return fusion
