"""The search that chooses a model's post-processing on validation scenes (parq_train.tune is
the command): a grid over score threshold, the local evaluation region and the scene fusion
(mode, minimum support, ray ratio), ranked by a :class:`Criterion`, then one pass per later
choice, each with everything before it in place.

Each validation snippet is run once with no threshold and no region
(parq_train.validation_runs); every candidate is then applied to those detections exactly as
the runtime applies it (after NMS), and the scene is fused and scored. So the grid costs one
detector pass, not one per candidate. Candidates that differ only in the minimum support share
one fusion (the support only filters its boxes), and ``jobs`` processes (tune's ``--jobs``, one
per core) share the rest: on 6 validation scenes with mirror runs, 19.6 s for 120 candidates
one by one, 8.3 s sharing fusions, 4.3 s in 2 processes (2-core EPYC), with the same table.

``mirror`` (tune's ``--mirror``) chooses for runs that add each snippet's mirror image
(parq-run --mirror, parq_runtime.mirror): the detector pass makes both runs, the grid's
supports count runs (1-4, twice the plain grid's), and the card records mirror runs in its run
setting, so parq-run makes them unless told ``--no-mirror``.

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
Last, the score threshold and the minimum support are chosen again, jointly, with all of that
in place (:func:`select_keep`): the grid fixed them before the rest changed
which boxes are right.

With tune's ``--phase-data`` (validation scenes rendered at least twice the network size each way,
for the demo the same rooms at 320x240), last of all: whether parq-run adds each snippet's
runs on the frames' second point-sampling grid (``run.phases``, parq_runtime.preprocess.grids)
and at which support (``postprocess.phase_support``), against one grid at the chosen support
(:func:`select_phases`; one grid wins ties).  At the network's own size a frame has one grid,
so the rest of the card is chosen there.
"""
from __future__ import annotations

import dataclasses
import multiprocessing as mp
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from parq_runtime import evaluation, floor
from parq_runtime.fusion import (AUTHORS_LABELS, AUTHORS_MIN_SUPPORT, AUTHORS_MODE,
                                 FLOOR_WEIGHT, LABEL_RULES, MATCH_IOU, RAY_RATIO, SceneFusion)
from parq_runtime.preprocess import PHASES

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


def kept_boxes(boxes: list, threshold: float, region) -> list:
    """The boxes of ``boxes`` ([(box, its local center)]) that a snippet keeps: scoring above
    ``threshold``, local center in ``region`` (xmin, xmax, zmin, zmax), as parq-run keeps
    them."""
    return [b for b, c in boxes if b.score > threshold
            and region[0] < c[0] < region[1] and region[2] < c[2] < region[3]]


def fuse_records(records: list, threshold: float, region, fusion: str,
                 ray_ratio: float = RAY_RATIO, mirror: bool = False,
                 scene_nms: float | None = None, labels: str = AUTHORS_LABELS,
                 match_iou: float = MATCH_IOU) -> list:
    """Per scene of ``records`` (run_once's): (its SceneFusion, support 1, of the snippet boxes
    scoring above ``threshold`` whose local centers lie in ``region``, truth, up); with
    ``mirror`` each snippet's mirror-image run is fused as parq-run --mirror fuses it
    (:func:`fuse_looks` of the records as looks at the first sampling grid)."""
    def looks(boxes):
        if mirror:
            return [(boxes[0], False, PHASES[0]), (boxes[1], True, PHASES[0])]
        return [(boxes, False, PHASES[0])]

    settings = {"score_threshold": threshold, "eval_region": region, "fusion": fusion,
                "ray_ratio": ray_ratio, "scene_nms": scene_nms, "labels": labels,
                "match_iou": match_iou}
    return fuse_looks([([looks(boxes) for boxes in snippets], truth, up)
                       for snippets, truth, up in records], settings, 1)


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
        return floor_row(fused, {**best, "floor_classes": floor_classes, "floor_weight": weight},
                         best["min_support"], classes, sweep)

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
    return floor_row(fused, settings, settings["min_support"], classes, sweep)


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
        rows += [floor_row(fused, {**best, "score_threshold": float(threshold)}, support,
                           classes, sweep) for support in supports]
    return best_of([best] + rows, criterion), rows


def fuse_looks(records: list, settings: dict, phases: int) -> list:
    """Per scene of ``records`` (run_looks'): (its SceneFusion, support 1, of the runs at the
    first ``phases`` sampling grids with ``settings``' threshold, region, fusion, ray ratio,
    scene NMS, label rule and matching IoU, truth, up)."""
    threshold, region = settings["score_threshold"], settings["eval_region"]
    fused = []
    for snippets, truth, up in records:
        scene_boxes = SceneFusion(settings["match_iou"], up=up, mode=settings["fusion"],
                                  ray_ratio=settings["ray_ratio"],
                                  scene_nms=settings["scene_nms"], labels=settings["labels"])
        for n, looks in enumerate(snippets):
            for boxes, mirrored, phase in looks:
                if phase in PHASES[:phases]:
                    scene_boxes.add(kept_boxes(boxes, threshold, region), n, mirrored, phase)
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
        return dict(floor_row(fused, best, support, classes, sweep), phases=phases)

    rows = [row(1, fuse_looks(records, best, 1), best["min_support"])]
    both = fuse_looks(records, best, 2)
    rows += [row(2, both, support) for support in range(1, 2 * (4 if mirror else 2) + 1)]
    chosen = best_of(rows, criterion)
    return ((2, chosen["min_support"]) if chosen["phases"] == 2 else (1, None)), rows


def floor_row(fused: list, settings: dict, min_support: int, classes, sweep) -> dict:
    """The row of ``settings`` (a row's CHOSEN keys; its floor prior applied as
    :func:`floor_pairs` applies it) at ``min_support``, scored on ``fused`` (fuse_records' or
    fuse_looks' with its threshold, region and fusion)."""
    pairs = floor_pairs(fused, min_support, settings["floor_classes"],
                        settings["floor_weight"], sweep)
    return scored_row(settings, min_support, evaluation.evaluate(pairs, classes))


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


def choose(records: list, classes, sweep, mirror: bool = False, jobs: int = 1,
           criterion: Criterion = SUM) -> tuple:
    """(the chosen row, the table of every row tried): :func:`select` over the grid (with or
    without ``mirror`` runs, in ``jobs`` processes), then :func:`select_scene_nms` for its
    best, then :func:`select_floor` with the floors ``sweep`` finds (validation_runs.floor_sweep
    of the records' scenes), then :func:`select_labels`, then :func:`select_match`, then
    :func:`select_keep`, each by ``criterion``; the table ends with the NMS rows, then the
    floor's, the label rules', the matching IoUs' and the last pass's."""
    best, table = select(records, classes, fusions=MIRROR_FUSIONS if mirror else FUSIONS,
                         mirror=mirror, jobs=jobs, criterion=criterion)
    best, rows = select_scene_nms(records, classes, best, mirror, criterion=criterion)
    best, floor_rows = select_floor(records, classes, best, sweep, mirror, criterion)
    best, label_rows = select_labels(records, classes, best, sweep, mirror, criterion)
    best, match_rows = select_match(records, classes, best, sweep, mirror, criterion)
    best, keep_rows = select_keep(records, classes, best, sweep, mirror, criterion)
    return best, table + rows + floor_rows + label_rows + match_rows + keep_rows
