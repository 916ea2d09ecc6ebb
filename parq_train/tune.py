"""Choose a trained model's post-processing on validation scenes: score threshold, the local
evaluation region (which snippet detections are kept before scene fusion), and the scene
fusion (mode, minimum support and, for ``ray`` fusion, the ray ratio; parq_runtime.fusion).

The authors fixed both for ScanNet (score > 0.8; centers with |x| < 1.5 m and z < 2 m in the
snippet frame).  A model trained here scores on a different scale and sees different rooms,
so the demo picks them on validation scenes (parq-synth seeds 2000 and 2001, never trained
on, never used for the reported numbers; ``--data`` pools several folders): the candidate that
maximises F1@0.25 + F1@0.5 at the run setting given (``--iters``, ``--queries``), or with
``--min-f1-50 F`` the best F1@0.25 among the candidates whose F1@0.5 is at least F
(:class:`Criterion`); ties go to the authors' fusion (best, support 1).  That setting is
written to the card as the one parq-run uses when not told (``run``), so the default run is
the one the post-processing was chosen for.

Each validation snippet is run once with no threshold and no region; every candidate is
then applied to those detections exactly as the runtime applies it (after NMS), and the scene
is fused and scored.  So the grid costs one detector pass, not one per candidate.  Candidates
that differ only in the minimum support share one fusion (the support only filters its
boxes), and ``--jobs`` processes (one per core) share the rest: on 6 validation scenes with
mirror runs, 19.6 s for 120 candidates one by one, 8.3 s sharing fusions, 4.3 s in 2
processes (2-core EPYC), with the same table.

``--mirror`` chooses for runs that add each snippet's mirror image (parq-run --mirror,
parq_runtime.mirror): the detector pass makes both runs, the grid's supports count runs (1-4,
twice the plain grid's), and the card records mirror runs in its run setting, so parq-run
makes them unless told ``--no-mirror``.

Then the scene NMS (parq_runtime.fusion: of two scene boxes of one class overlapping by more
than an IoU, only the better-scoring is reported) is chosen for the best candidate: off, or
one of SCENE_NMS, by the same criterion, off winning ties.  It comes after the grid, not in it,
so that it does not multiply the grid's time; it only removes boxes that the chosen candidate
keeps.

Then the floor prior (parq_runtime.fusion, parq_runtime.floor: boxes of floor-standing classes
pulled to stand on the floor found in the images) is chosen for that: off, or a set of classes
and a weight (FLOOR_WEIGHTS).  The set starts from the classes that stand on their scene's
floor in the validation ground truth (at least STANDING_SHARE of their boxes have their
bottom within STANDING_TOLERANCE of the lowest box bottom), and classes are then dropped one
at a time while that raises the criterion (backward elimination); off wins ties.  Each scene's
floor is found as parq-run finds it, from its frames near the fused boxes' guess.

Then the label rule (parq_runtime.fusion ``labels``: a scene box reports its best detection's
class, or the class its detections vote for) is chosen for all of that, the authors' rule
winning ties, and then the fusion's matching IoU (MATCH_IOUS; the authors' 0.1 winning ties).
Last, the score threshold and the minimum support are chosen again, jointly,
with all of that in place (:func:`select_keep`): the grid fixed them before the rest changed
which boxes are right.

With ``--phase-data`` (validation scenes rendered at least twice the network size each way,
for the demo the same rooms at 320x240), last of all: whether parq-run adds each snippet's
runs on the frames' second point-sampling grid (``run.phases``, parq_runtime.preprocess.grids)
and at which support (``postprocess.phase_support``), against one grid at the chosen support
(:func:`select_phases`; one grid wins ties).  At the network's own size a frame has one grid,
so the rest of the card is chosen there.

Before all of this, a checkpoint's learned queries are ranked (``query_order``, see
parq_runtime.queries; a model folder keeps its own ranking): one pass with all of them, each
query scored by the snippet detections it makes above score 0.7, +1 for each that overlaps a
ground-truth box of its class at IoU 0.25 and -0.5 for each that does not.  Runs with fewer
queries start from the best ones, and the post-processing is chosen for that subset.

    python -m parq_train.tune work/demo.pt --data data/val data/val2 --queries 64 \
        -o work/demo-tuned.pt
    python -m parq_train.tune models/parq-demo --data data/val data/val2 --queries 64 \
        --mirror -o work/parq-demo-tuned

Given a checkpoint it writes a checkpoint (parq-export it next).  Given an exported model
folder it writes a copy of the folder whose card (and the graphs' mirrored cards) hold the
new choice; the folder's query order is kept, so the same weights give the same card either
way when the folder's order is what tuning its checkpoint ranked.
"""
from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import pathlib
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from parq_runtime import evaluation, floor, geometry, preprocess, readers, scene
from parq_runtime.preprocess import PHASES
from parq_runtime.arguments import OneLineParser, fraction, positive_int
from parq_runtime.errors import ParqError
from parq_runtime.fusion import (AUTHORS_LABELS, AUTHORS_MIN_SUPPORT, AUTHORS_MODE,
                                 FLOOR_WEIGHT, LABEL_RULES, MATCH_IOU, RAY_RATIO, SceneFusion)
from parq_runtime.iou import iou_matrix

THRESHOLDS = tuple(np.round(np.arange(0.3, 0.951, 0.05), 2))
# (xmin, xmax, zmin, zmax) in the snippet frame; the first is the authors'.
REGIONS = ((-1.5, 1.5, 0.0, 2.0), (-2.0, 2.0, 0.0, 3.0), (-2.5, 2.5, 0.0, 3.5),
           (-3.0, 3.0, 0.0, 4.5), (-10.0, 10.0, -10.0, 10.0))
# (mode, min_support, ray_ratio); the first is the authors'.  No support above 2: it would hide
# every object that a short capture shows in fewer snippets (3 snippets are 9 keyframes).
RAY_RATIOS = (3.0, 10.0, 30.0)
FUSIONS = ((AUTHORS_MODE, AUTHORS_MIN_SUPPORT, RAY_RATIO), ("best", 2, RAY_RATIO),
           ("mean", 1, RAY_RATIO), ("mean", 2, RAY_RATIO)) + tuple(
    ("ray", support, ratio) for support in (1, 2) for ratio in RAY_RATIOS)
# With mirror runs support counts runs, two a snippet: supports up to twice the grid's above.
MIRROR_FUSIONS = ((AUTHORS_MODE, AUTHORS_MIN_SUPPORT, RAY_RATIO),) + tuple(
    (mode, support, ratio) for mode, ratio in (("best", RAY_RATIO), ("mean", RAY_RATIO))
    + tuple(("ray", r) for r in RAY_RATIOS) for support in (1, 2, 3, 4)
    if (mode, support) != (AUTHORS_MODE, AUTHORS_MIN_SUPPORT))
RANKING_SCORE, RANKING_IOU, FALSE_WEIGHT = 0.7, 0.25, 0.5  # how query_utility counts
AUTHORS = {"score_threshold": 0.8, "eval_region": list(REGIONS[0]), "fusion": FUSIONS[0][0],
           "min_support": FUSIONS[0][1], "scene_nms": None, "labels": AUTHORS_LABELS}
CHOSEN = ("score_threshold", "eval_region", "fusion", "min_support", "ray_ratio", "scene_nms",
          "floor_classes", "floor_weight", "labels", "match_iou")
SCENE_NMS = (None, 0.0, 0.05, 0.1, 0.2, 0.3)   # None: off, the authors' protocol
FLOOR_WEIGHTS = (FLOOR_WEIGHT, 10.0)           # the first is the runtime's default
MATCH_IOUS = (MATCH_IOU, 0.05, 0.02, 0.01)      # the first is the authors'
STANDING_SHARE, STANDING_TOLERANCE = 0.9, 0.02  # a floor class: 90% of its boxes within 2 cm


@dataclasses.dataclass(frozen=True)
class Criterion:
    """How the candidates are ranked.  ``min_f1_50`` None: by F1@0.25 + F1@0.5 (then
    F1@0.5), the demo's first criterion.  A number: by F1@0.25 (then F1@0.5) among the
    candidates whose F1@0.5 is at least that, every one of which ranks above every candidate
    below it (those by the sum): the issue's goal is a floor at IoU 0.5 and a level at 0.25,
    so the validation scenes choose the best F1@0.25 that keeps IoU 0.5 clear of its floor."""
    min_f1_50: float | None = None

    def key(self, row: dict) -> tuple:
        total = row["f1@0.25"] + row["f1@0.5"]
        if self.min_f1_50 is None:
            return (total, row["f1@0.5"])
        clear = row["f1@0.5"] >= self.min_f1_50
        return (clear, row["f1@0.25"] if clear else total, row["f1@0.5"])

    def describe(self) -> str:
        if self.min_f1_50 is None:
            return "max F1@0.25 + F1@0.5"
        return f"max F1@0.25 with F1@0.5 >= {self.min_f1_50:g}"


SUM = Criterion()


def run_once(detector, folders, iters: int, queries: int, stride: int | None = None,
             mirror: bool = False) -> list:
    """Per scene: (snippets as [(box, its local center)], truth, up); ``stride``: keyframes
    between snippet starts (None: parq-run's default, no overlap); ``mirror``: each snippet is
    a pair (plain, mirrored) of such lists, the second from its mirror-image run."""
    def record(s, local, phases):
        return (local(s.boxes), local(s.mirrored)) if mirror else local(s.boxes)

    return detect_scenes(detector, folders, scene.RunSettings(
        iters=iters, queries=queries, score_threshold=0.0, region=False, stride=stride,
        mirror=mirror, phases=1), record)


def run_looks(detector, folders, iters: int, queries: int, mirror: bool) -> list:
    """Per scene: (snippets, truth, up), a snippet a list of its runs (looks) as (boxes as
    [(box, its local center)], mirrored, phase), each snippet run at both point-sampling
    grids (parq-run --phases 2; scenes whose frames have one grid get one) and, with
    ``mirror``, each also mirrored."""
    def record(s, local, phases):
        looks = [(local(s.boxes), False, 0.0)]
        if mirror:
            looks.append((local(s.mirrored), True, 0.0))
        if phases > 1:
            looks.append((local(s.phased), False, PHASES[1]))
            if mirror:
                looks.append((local(s.phased_mirrored), True, PHASES[1]))
        return looks

    return detect_scenes(detector, folders, scene.RunSettings(
        iters=iters, queries=queries, score_threshold=0.0, region=False, mirror=mirror,
        phases=2), record)


def detect_scenes(detector, folders, settings, record) -> list:
    """Per scene of ``folders``: ([record(snippet, local, phases) for each snippet of one
    scene.run at ``settings``], truth, up), where ``local(boxes)`` pairs each box with its
    center in that snippet's frame and ``phases`` is the sampling grids the scene was run at:
    what run_once and run_looks share."""
    out = []
    for folder in folders:
        result = scene.run(detector, readers.open_capture(folder), settings)
        snippets = []
        for s in result.snippets:
            T_local_world = geometry.invert(s.T_world_local)

            def local(boxes):
                return [(b, geometry.transform(T_local_world, b.center)) for b in boxes]

            snippets.append(record(s, local, result.phases))
        truth, up = evaluation.load_ground_truth(folder / "boxes.json")
        out.append((snippets, truth, up))
    return out


def query_utility(records: list, num_queries: int) -> np.ndarray:
    """(num_queries,) true minus FALSE_WEIGHT x false snippet detections of each query over
    ``records`` (run_once with every learned query): a detection scoring above RANKING_SCORE
    is true when it overlaps a ground-truth box of its class at IoU >= RANKING_IOU."""
    utility = np.zeros(num_queries)
    for snippets, truth, up in records:
        for boxes in snippets:
            for box, _ in boxes:
                if box.score <= RANKING_SCORE:
                    continue
                same = [t for t in truth if t.class_name == box.class_name]
                hit = bool(same) and iou_matrix([box], same, up).max() >= RANKING_IOU
                utility[box.query] += 1.0 if hit else -FALSE_WEIGHT
    return utility


def rank_queries(utility: np.ndarray) -> list:
    """Query indices by decreasing utility; equal ones keep their stored order."""
    return [int(i) for i in np.argsort(-utility, kind="stable")]


def score(records: list, threshold: float, region, classes, fusion: str = AUTHORS_MODE,
          min_support: int = AUTHORS_MIN_SUPPORT, ray_ratio: float = RAY_RATIO,
          mirror: bool = False, scene_nms: float | None = None) -> dict:
    """parq-eval metrics of the scenes fused with ``fusion``, ``min_support`` and ``ray_ratio``
    when snippets keep boxes scoring above ``threshold`` whose local centers lie in
    ``region``; ``mirror``: the records are run_once's with mirror runs, fused as parq-run
    --mirror fuses them."""
    return score_supports(records, threshold, region, classes, fusion, (min_support,),
                          ray_ratio, mirror, scene_nms)[min_support]


def score_supports(records: list, threshold: float, region, classes, fusion: str,
                   supports, ray_ratio: float = RAY_RATIO, mirror: bool = False,
                   scene_nms: float | None = None) -> dict:
    """{support: :func:`score`'s metrics} for each of ``supports``, from one fusion of each
    scene (the support only filters the fused boxes)."""
    fused = fuse_records(records, threshold, region, fusion, ray_ratio, mirror, scene_nms)
    return {s: evaluation.evaluate([(f.boxes_with_support(s), truth, up)
                                    for f, truth, up in fused], classes) for s in supports}


def fuse_records(records: list, threshold: float, region, fusion: str,
                 ray_ratio: float = RAY_RATIO, mirror: bool = False,
                 scene_nms: float | None = None, labels: str = AUTHORS_LABELS,
                 match_iou: float = MATCH_IOU) -> list:
    """Per scene of ``records`` (run_once's): (its SceneFusion, support 1, of the snippet boxes
    scoring above ``threshold`` whose local centers lie in ``region``, truth, up); with
    ``mirror`` each snippet's mirror-image run is fused as parq-run --mirror fuses it."""
    def kept(boxes):
        return [b for b, c in boxes if b.score > threshold
                and region[0] < c[0] < region[1] and region[2] < c[2] < region[3]]

    fused = []
    for snippets, truth, up in records:
        scene_boxes = SceneFusion(match_iou, up=up, mode=fusion, ray_ratio=ray_ratio,
                                  scene_nms=scene_nms, labels=labels)
        for n, boxes in enumerate(snippets):
            if mirror:
                scene_boxes.add(kept(boxes[0]), n)
                scene_boxes.add(kept(boxes[1]), n, mirrored=True)
            else:
                scene_boxes.add(kept(boxes), n)
        fused.append((scene_boxes, truth, up))
    return fused


def select(records: list, classes, thresholds=THRESHOLDS, regions=REGIONS,
           fusions=FUSIONS, mirror: bool = False, jobs: int = 1,
           criterion: Criterion = SUM) -> tuple:
    """(the best candidate's row by ``criterion``, table of every candidate's settings and
    F1s), candidates in the order fusion, region, threshold.  A row holds score_threshold,
    eval_region, fusion, min_support, ray_ratio and f1@0.25, f1@0.5, f1@0.7.  ``mirror``: the
    records hold mirror runs (run_once).  Candidates that differ only in support share one
    fusion; ``jobs`` processes share the rest (the table is the same for any number)."""
    supports = {}
    for mode, support, ratio in fusions:
        supports.setdefault((mode, ratio), []).append(support)
    tasks = [(float(t), tuple(region), mode, tuple(s), ratio)
             for (mode, ratio), s in supports.items() for region in regions for t in thresholds]
    found = {_key(row["fusion"], row["min_support"], row["ray_ratio"], row["eval_region"],
                  row["score_threshold"]): row
             for rows in _map(_candidates, tasks, records, classes, mirror, jobs) for row in rows}
    table = [found[_key(mode, support, ratio, region, t)]
             for mode, support, ratio in fusions for region in regions for t in thresholds]
    return best_of(table, criterion), table


def _key(fusion: str, min_support: int, ray_ratio: float, region, threshold) -> tuple:
    """A candidate's settings, hashable: where :func:`select` files its table row."""
    return fusion, min_support, ray_ratio, tuple(region), float(threshold)


_SHARED = {}   # what _candidates reads in a worker process (inherited by fork, not pickled)


def _map(function, tasks, records, classes, mirror, jobs) -> list:
    """[function(task) for task in tasks] with the records shared, in ``jobs`` processes.
    The workers are forked, so they read the records without copying or pickling them; fork
    is only safe on Linux (macOS's system libraries are not fork-safe), so elsewhere the
    tasks run in this process."""
    _SHARED.update(records=records, classes=classes, mirror=mirror)
    try:
        if jobs <= 1 or len(tasks) < 2 or not sys.platform.startswith("linux"):
            return [function(task) for task in tasks]
        with ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork")) as pool:
            return list(pool.map(function, tasks, chunksize=4))
    finally:
        _SHARED.clear()


def _candidates(task) -> list:
    """The table rows of one (threshold, region, mode, supports, ratio) task."""
    threshold, region, mode, supports, ratio = task
    metrics = score_supports(_SHARED["records"], threshold, region, _SHARED["classes"], mode,
                             supports, ratio, _SHARED["mirror"])
    return [row_of(threshold, region, mode, s, ratio, metrics[s]) for s in supports]


def candidate(records: list, classes, threshold: float, region, fusion: str, min_support: int,
              ray_ratio: float, mirror: bool = False, scene_nms: float | None = None) -> dict:
    """One row of :func:`select`'s table: the settings and the F1s they give on ``records``."""
    m = score(records, threshold, region, classes, fusion, min_support, ray_ratio, mirror,
              scene_nms)
    return row_of(threshold, region, fusion, min_support, ray_ratio, m, scene_nms)


def row_of(threshold: float, region, fusion: str, min_support: int, ray_ratio: float,
           metrics: dict, scene_nms: float | None = None, floor_classes=(),
           floor_weight: float = FLOOR_WEIGHT, labels: str = AUTHORS_LABELS,
           match_iou: float = MATCH_IOU) -> dict:
    return {"score_threshold": threshold, "eval_region": list(region), "fusion": fusion,
            "min_support": min_support, "ray_ratio": ray_ratio, "scene_nms": scene_nms,
            "floor_classes": list(floor_classes), "floor_weight": floor_weight,
            "labels": labels, "match_iou": match_iou,
            **{f"f1@{k}": round(metrics[k]["f1"], 4) for k in metrics}}


def select_scene_nms(records: list, classes, best: dict, mirror: bool = False,
                     choices=SCENE_NMS, criterion: Criterion = SUM) -> tuple:
    """(the best of ``best`` with each scene NMS of ``choices``, their rows), by
    :func:`best_of` with ``criterion``: the first choice (off) wins ties."""
    keys = CHOSEN[:CHOSEN.index("scene_nms")]         # candidate()'s order
    rows = [candidate(records, classes, *(best[k] for k in keys), mirror, nms)
            for nms in choices]
    return best_of(rows, criterion), rows


def standing_classes(records: list, classes) -> list:
    """The classes (in ``classes``' order) of which at least STANDING_SHARE of the ground-truth
    boxes in ``records`` have their bottom within STANDING_TOLERANCE of their scene's floor,
    taken as the lowest box bottom of the scene."""
    standing, seen = {}, {}
    for _, truth, up in records:
        if not truth:
            continue
        up = np.asarray(up, dtype=np.float64)
        bottoms = [float(b.center @ up) - b.size[1] / 2 for b in truth]
        lowest = min(bottoms)
        for b, bottom in zip(truth, bottoms):
            seen[b.class_name] = seen.get(b.class_name, 0) + 1
            standing[b.class_name] = standing.get(b.class_name, 0) + (
                bottom - lowest <= STANDING_TOLERANCE)
    return [c for c in classes if seen.get(c) and standing[c] >= STANDING_SHARE * seen[c]]


def select_floor(records: list, classes, best: dict, sweep, mirror: bool = False,
                 criterion: Criterion = SUM) -> tuple:
    """(``best`` with the floor prior chosen, the rows tried): off, then the standing classes
    at each of FLOOR_WEIGHTS, then backward elimination of classes at the better weight, by
    :func:`best_of` with ``criterion`` (off, and the larger set, win ties).
    ``sweep(scene, guess)``: the floor candidates of the ``scene``-th scene of ``records``
    near ``guess`` (floor.candidates); a floor is chosen from them as parq-run chooses it."""
    fused = fuse_records(records, best["score_threshold"], best["eval_region"], best["fusion"],
                         best["ray_ratio"], mirror, best["scene_nms"])

    def row(floor_classes, weight):
        pairs = floor_pairs(fused, best["min_support"], floor_classes, weight, sweep)
        return row_of(best["score_threshold"], best["eval_region"], best["fusion"],
                      best["min_support"], best["ray_ratio"], evaluation.evaluate(pairs, classes),
                      best["scene_nms"], floor_classes, weight)

    rows = [row((), FLOOR_WEIGHT)]
    chosen = standing_classes(records, classes)
    if not chosen or best["fusion"] != "ray":
        return rows[0], rows
    rows += [row(chosen, w) for w in FLOOR_WEIGHTS]
    current = best_of(rows[1:], criterion)
    weight = current["floor_weight"]
    while len(chosen) > 1:
        tried = [row([c for c in chosen if c != drop], weight) for drop in chosen]
        rows += tried
        better = best_of([current] + tried, criterion)
        if better is current:
            break
        current, chosen = better, better["floor_classes"]
    return best_of([rows[0], current], criterion), rows


def floor_pairs(fused: list, min_support: int, floor_classes, weight: float, sweep) -> list:
    """(scene boxes, truth, up) per scene of ``fused`` (fuse_records') at ``min_support``,
    the boxes of ``floor_classes`` pulled at ``weight`` to the floor parq-run would find
    (``sweep``: as for :func:`select_floor`)."""
    pairs = []
    for n, (fusion, truth, up) in enumerate(fused):
        fusion.min_support = min_support
        fusion.floor_classes, fusion.floor_weight = tuple(floor_classes), weight
        fusion.floor_height = floor.locate(fusion.floor_guess(),
                                           lambda guess: sweep(n, guess))[0] \
            if floor_classes else None
        pairs.append((fusion.boxes, truth, up))
    return pairs


def select_labels(records: list, classes, best: dict, sweep, mirror: bool = False,
                  criterion: Criterion = SUM) -> tuple:
    """(``best`` with the label rule chosen by ``criterion``, the rows tried): ``best``
    itself, scored with the authors' rule (which wins ties; parq_runtime.fusion), then each
    other rule of LABEL_RULES with everything else ``best``'s, floor prior included."""
    rows = [best] + [scored(records, classes, dict(best, labels=labels), sweep, mirror)
                     for labels in LABEL_RULES if labels != best["labels"]]
    return best_of(rows, criterion), rows


def scored(records: list, classes, settings: dict, sweep, mirror: bool = False) -> dict:
    """The row of ``settings`` (a row's CHOSEN keys): the records fused, pulled to the floor
    (``sweep``: as for :func:`select_floor`) and scored as parq-run would run them."""
    fused = fuse_records(records, settings["score_threshold"], settings["eval_region"],
                         settings["fusion"], settings["ray_ratio"], mirror,
                         settings["scene_nms"], settings["labels"], settings["match_iou"])
    pairs = floor_pairs(fused, settings["min_support"], settings["floor_classes"],
                        settings["floor_weight"], sweep)
    return scored_row(settings, settings["min_support"], evaluation.evaluate(pairs, classes))


def select_match(records: list, classes, best: dict, sweep, mirror: bool = False,
                 criterion: Criterion = SUM) -> tuple:
    """(``best`` with the fusion's matching IoU chosen by ``criterion``, the rows tried):
    ``best`` itself (the authors' 0.1, which wins ties), then each other IoU of MATCH_IOUS with
    everything else ``best``'s.  A lower floor joins more of one object's detections into one
    scene box, and so raises its support: :func:`select_keep`, after it, chooses the support
    again with it (docs/demo-experiments.md, "The fusion's matching IoU")."""
    rows = [best] + [scored(records, classes, dict(best, match_iou=match_iou), sweep, mirror)
                     for match_iou in MATCH_IOUS if match_iou != best["match_iou"]]
    return best_of(rows, criterion), rows


def select_keep(records: list, classes, best: dict, sweep, mirror: bool = False,
                criterion: Criterion = SUM) -> tuple:
    """(``best`` with the score threshold and minimum support chosen again, jointly, by
    ``criterion``, the rows tried): every threshold of THRESHOLDS with every support the
    grid allows (1-4 with mirror runs, else 1-2), everything else ``best``'s, scene NMS,
    floor prior and label rule included; ``best`` wins ties.  The grid chose both before the
    NMS, the floor and the vote changed which boxes are right, and they trade precision for
    recall together; this pass lets them move with what came after (the demo's card:
    support 4 -> 3 at threshold 0.8, docs/demo-experiments.md)."""
    supports = range(1, 5 if mirror else 3)
    rows = []
    for threshold in THRESHOLDS:
        fused = fuse_records(records, threshold, best["eval_region"], best["fusion"],
                             best["ray_ratio"], mirror, best["scene_nms"], best["labels"],
                             best["match_iou"])
        for support in supports:
            pairs = floor_pairs(fused, support, best["floor_classes"], best["floor_weight"],
                                sweep)
            rows.append(row_of(float(threshold), best["eval_region"], best["fusion"], support,
                               best["ray_ratio"], evaluation.evaluate(pairs, classes),
                               best["scene_nms"], best["floor_classes"], best["floor_weight"],
                               best["labels"], best["match_iou"]))
    return best_of([best] + rows, criterion), rows


def fuse_looks(records: list, settings: dict, phases: int) -> list:
    """Per scene of ``records`` (run_looks'): (its SceneFusion, support 1, of the runs at the
    first ``phases`` sampling grids with ``settings``' threshold, region and fusion, truth,
    up)."""
    threshold, region = settings["score_threshold"], settings["eval_region"]
    fused = []
    for snippets, truth, up in records:
        scene_boxes = SceneFusion(settings["match_iou"], up=up, mode=settings["fusion"],
                                  ray_ratio=settings["ray_ratio"],
                                  scene_nms=settings["scene_nms"], labels=settings["labels"])
        for n, looks in enumerate(snippets):
            for boxes, mirrored, phase in looks:
                if phase in PHASES[:phases]:
                    scene_boxes.add([b for b, c in boxes if b.score > threshold
                                     and region[0] < c[0] < region[1]
                                     and region[2] < c[2] < region[3]], n, mirrored, phase)
        fused.append((scene_boxes, truth, up))
    return fused


def select_phases(records: list, classes, best: dict, sweep, mirror: bool = False,
                  criterion: Criterion = SUM) -> tuple:
    """((phases, phase_support), the rows tried) on ``records`` (run_looks' of scenes whose
    frames are at least twice the network size; ``sweep`` their floors): ``best`` at one
    sampling grid, its own support, against both grids at every support from 1 to twice
    :func:`select_keep`'s largest (the support counts runs, twice as many); one grid wins ties
    (docs/demo-experiments.md, "Frames larger than the network")."""
    def row(phases, fused, support):
        pairs = floor_pairs(fused, support, best["floor_classes"], best["floor_weight"], sweep)
        return dict(scored_row(best, support, evaluation.evaluate(pairs, classes)),
                    phases=phases)

    rows = [row(1, fuse_looks(records, best, 1), best["min_support"])]
    both = fuse_looks(records, best, 2)
    rows += [row(2, both, support) for support in range(1, 2 * (4 if mirror else 2) + 1)]
    chosen = best_of(rows, criterion)
    return ((2, chosen["min_support"]) if chosen["phases"] == 2 else (1, None)), rows


def scored_row(settings: dict, min_support: int, metrics: dict) -> dict:
    """row_of ``settings`` (a row's CHOSEN keys) at ``min_support`` with ``metrics``."""
    return row_of(settings["score_threshold"], settings["eval_region"], settings["fusion"],
                  min_support, settings["ray_ratio"], metrics, settings["scene_nms"],
                  settings["floor_classes"], settings["floor_weight"], settings["labels"],
                  settings["match_iou"])


def best_of(table: list, criterion: Criterion = SUM) -> dict:
    """The best row of ``table`` by ``criterion``; max() keeps the first of equals, so in
    :func:`select`'s table the authors' fusion wins ties."""
    return max(table, key=criterion.key)


def main(argv=None) -> int:
    # the docstring's first paragraph: its first line alone stops mid-sentence
    p = OneLineParser(prog="python -m parq_train.tune",
                      description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("checkpoint", type=pathlib.Path,
                   help="trained checkpoint (parq-train), or a model folder (parq-export)")
    p.add_argument("--data", type=pathlib.Path, nargs="+", default=[pathlib.Path("data/val")],
                   help="one or more folders of validation scenes, pooled (default data/val: "
                        "parq-synth seed 2000)")
    p.add_argument("--scenes", type=positive_int, default=None,
                   help="use the first N scenes of each --data folder (default: all)")
    p.add_argument("--iters", type=positive_int, default=2,
                   help="iterations to choose the post-processing for; the card records them "
                        "as parq-run's default (default 2)")
    p.add_argument("--queries", type=positive_int, default=32,
                   help="queries to choose the post-processing for; the card records them as "
                        "parq-run's default (default 32; the demo's 64)")
    p.add_argument("--mirror", action="store_true",
                   help="choose the post-processing for runs that add each snippet's mirror "
                        "image (parq-run --mirror; supports up to 4 runs); the card records "
                        "mirror runs as parq-run's default")
    p.add_argument("--phase-data", type=pathlib.Path, nargs="+", default=None, metavar="DIR",
                   help="also choose whether parq-run adds the second point-sampling grid "
                        "(--phases 2) and its support, on these validation scenes rendered at "
                        "least twice the network size each way (the --data scenes at 320x240 "
                        "for the demo); model folders only (default: not chosen, one grid)")
    p.add_argument("--min-f1-50", type=fraction, default=None, metavar="F",
                   help="choose the candidate with the best F1@0.25 among those whose F1@0.5 "
                        "on the validation scenes is at least F (default: the best F1@0.25 + "
                        "F1@0.5)")
    p.add_argument("--jobs", type=positive_int, default=os.cpu_count() or 1,
                   help="processes that score the candidates (default: one per core; the "
                        "choice is the same for any number)")
    p.add_argument("-o", "--output", type=pathlib.Path, required=True,
                   help="checkpoint to write with the chosen post-processing (for a model "
                        "folder: the new model folder, which must not exist)")
    args = p.parse_args(argv)
    try:
        return run(args)
    except ParqError as e:
        print(f"parq_train.tune: error: {e}", file=sys.stderr)
        return 2


def criterion_of(args) -> Criterion:
    """The :class:`Criterion` that ``args`` (main's) ask for."""
    return Criterion(getattr(args, "min_f1_50", None))


def record_of(args, folders, best, table, ranking) -> dict:
    """What the card's ``extra.postprocess_tuning`` says about a tuning run."""
    authors = next(r for r in table if all(r[k] == v for k, v in AUTHORS.items()))
    seeds = sorted({json.loads((f / "scene.json").read_text()).get("seed") for f in folders
                    if (f / "scene.json").exists()})
    return {"data": [str(d) for d in args.data], "seeds": seeds, "scenes": len(folders),
            "iters": args.iters, "queries": args.queries, "mirror": args.mirror,
            "criterion": criterion_of(args).describe(),
            "chosen": best, "authors_settings": authors, "query_ranking": ranking}


def choose(records: list, classes, args, folders: list) -> tuple:
    """:func:`select` over the grid for the run setting of ``args`` (with or without mirror
    runs), then :func:`select_scene_nms` for its best, then :func:`select_floor` with the
    floors of the scenes ``folders``, then :func:`select_labels`, then :func:`select_match`,
    then :func:`select_keep`; the table ends with the NMS rows, then the floor's, the label
    rules', the matching IoUs' and the last pass's."""
    criterion = criterion_of(args)
    best, table = select(records, classes, fusions=MIRROR_FUSIONS if args.mirror else FUSIONS,
                         mirror=args.mirror, jobs=args.jobs, criterion=criterion)
    best, rows = select_scene_nms(records, classes, best, args.mirror, criterion=criterion)
    sweep = floor_sweep(folders)
    best, floor_rows = select_floor(records, classes, best, sweep, args.mirror, criterion)
    best, label_rows = select_labels(records, classes, best, sweep, args.mirror, criterion)
    best, match_rows = select_match(records, classes, best, sweep, args.mirror, criterion)
    best, keep_rows = select_keep(records, classes, best, sweep, args.mirror, criterion)
    return best, table + rows + floor_rows + label_rows + match_rows + keep_rows


def floor_sweep(folders: list):
    """select_floor's ``sweep`` for the validation scenes ``folders`` (records' order): each
    scene's floor candidates near a guess, as parq-run computes them (cached per guess)."""
    captures, cache = {}, {}

    def sweep(n: int, guess: float) -> list:
        if (n, guess) not in cache:
            if n not in captures:
                captures[n] = readers.open_capture(folders[n])
            capture = captures[n]
            cache[n, guess] = floor.candidates(capture.frames, capture.up, near=guess)
        return cache[n, guess]
    return sweep


def run(args) -> int:
    folders = validation_folders(args.data, args.scenes)
    if args.checkpoint.is_dir():
        return run_folder(args, folders)
    return run_checkpoint(args, folders)


def validation_folders(data: list, scenes: int | None) -> list:
    """The scenes of each folder in ``data`` (its first ``scenes``, or all), in order; a folder
    without generated scenes is an error."""
    folders = []
    for folder in data:
        found = sorted(p.parent for p in pathlib.Path(folder).glob("*/boxes.json"))
        if not found:
            raise ParqError(f"{folder}: no generated scenes (parq-synth)")
        folders += found[:scenes]
    return folders


def run_folder(args, folders) -> int:
    """Tune an exported model folder; writes a copy with the new card (module doc)."""
    from parq_export import card_rewrite
    from parq_runtime import Detector

    detector = Detector(args.checkpoint)
    if args.output.exists():
        raise ParqError(f"{args.output}: already exists (a model folder is written new)")
    phase_folders = validation_folders(args.phase_data, args.scenes) if args.phase_data else []
    check_two_grids(phase_folders, detector.card)
    records = run_once(detector, folders, args.iters, args.queries, mirror=args.mirror)
    best, table = choose(records, detector.classes, args, folders)
    phases, phase_support = 1, None
    if phase_folders:
        looks = run_looks(detector, phase_folders, args.iters, args.queries, args.mirror)
        (phases, phase_support), phase_rows = select_phases(
            looks, detector.classes, best, floor_sweep(phase_folders), args.mirror,
            criterion_of(args))
        table += phase_rows
    previous = detector.card.raw.get("extra", {}).get("postprocess_tuning") or {}
    ranking = previous.get("query_ranking")
    if ranking:
        ranking = dict(ranking, kept_from=str(args.checkpoint))
    record = dict(record_of(args, folders, best, table, ranking),
                  tuned=f"model folder {args.checkpoint}", phases=phases,
                  phase_support=phase_support,
                  phase_data=[str(d) for d in args.phase_data or ()])

    def update(card):
        card["postprocess"].update({k: best[k] for k in CHOSEN}, phase_support=phase_support)
        card["run"] = {"iters": args.iters, "queries": args.queries, "mirror": args.mirror,
                       "phases": phases}
        card["extra"] = dict(card.get("extra", {}), postprocess_tuning=record)
    card_rewrite.rewrite(args.checkpoint, args.output, update)
    print(json.dumps(record, indent=1))
    return 0


def check_two_grids(folders: list, card) -> None:
    """ParqError unless every scene of ``folders`` has frames with two point-sampling grids
    for ``card``'s network (preprocess.grids; its first frame stands for the scene)."""
    for folder in folders:
        height, width = readers.open_capture(folder).frames[0].load_image().shape[:2]
        if preprocess.grids((width, height), card.image_size, card.image_filter) < 2:
            w, h = card.image_size
            raise ParqError(f"{folder}: its {width}x{height} frames have one point-sampling "
                            f"grid for this {w}x{h} model ({card.image_filter!r} filter); "
                            f"--phase-data needs frames at least twice its size each way")


def run_checkpoint(args, folders) -> int:
    from parq_export import checkpoint
    from parq_export.export import export
    from parq_runtime import Detector

    if getattr(args, "phase_data", None):
        raise ParqError("--phase-data chooses for a model folder: export the checkpoint, then "
                        "tune the folder")

    loaded = checkpoint.load(args.checkpoint)
    learned = loaded.config.num_queries
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        export(args.checkpoint, tmp / "model", log=lambda *_: None)
        detector = Detector(tmp / "model")
        # the ranking is recorded whatever --queries is, so that a run with fewer queries
        # than the card's setting starts from the best ones
        records = run_once(detector, folders, args.iters, learned)
        utility = query_utility(records, learned)
        order = rank_queries(utility)
        ranking = {"utility": [float(u) for u in utility], "order": order,
                   "criterion": f"snippet detections above {RANKING_SCORE}: +1 if IoU >= "
                                f"{RANKING_IOU} with a box of its class, else "
                                f"-{FALSE_WEIGHT}", "iters": args.iters}
        if args.queries < learned:
            ranked = loaded.model()
            ranked.config = loaded.config.replace(query_order=tuple(order))
            checkpoint.save(tmp / "ranked.pt", ranked, {})
            export(tmp / "ranked.pt", tmp / "ranked", log=lambda *_: None)
            detector = Detector(tmp / "ranked")
        if args.queries != learned or args.mirror:
            records = run_once(detector, folders, args.iters, args.queries,
                               mirror=args.mirror)
        classes = detector.classes
    best, table = choose(records, classes, args, folders)
    record = record_of(args, folders, best, table, ranking)
    model = loaded.model()
    extra = dict(loaded.config.extra, postprocess_tuning=record)
    model.config = loaded.config.replace(
        score_threshold=best["score_threshold"], eval_region=tuple(best["eval_region"]),
        fusion=best["fusion"], min_support=best["min_support"], ray_ratio=best["ray_ratio"],
        scene_nms=best["scene_nms"], floor_classes=tuple(best["floor_classes"]),
        floor_weight=best["floor_weight"], labels=best["labels"], match_iou=best["match_iou"],
        run_iters=args.iters, run_queries=args.queries, run_mirror=args.mirror, extra=extra,
        query_order=tuple(order))
    metadata = {"tuning_table": table}
    checkpoint.save(args.output, model, metadata)
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
