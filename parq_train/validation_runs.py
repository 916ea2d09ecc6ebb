"""The detector's pass over validation scenes that parq_train.tune (and the benchmarks) score:
each scene run as parq-run runs it (parq_runtime.scene) but with no score threshold and no
region, each snippet's boxes paired with their centers in its snippet frame, so that every
post-processing candidate can be applied to the same detections afterwards
(parq_train.postprocess_search); the learned queries' ranking by those detections; the
validation folders and their floors.

Records, per scene: (snippets, truth, up).  :func:`run_once` makes a snippet a list of
(box, local center) pairs, or with mirror runs a pair (plain, mirrored) of such lists;
:func:`run_looks` makes it a list of looks (boxes, mirrored, phase), one per run of the snippet
at each point-sampling grid (parq-run --phases 2).
"""
from __future__ import annotations

import pathlib

import numpy as np

from parq_runtime import evaluation, floor, geometry, readers, scene
from parq_runtime.errors import ParqError
from parq_runtime.iou import iou_matrix
from parq_runtime.preprocess import PHASES

RANKING_SCORE, RANKING_IOU, FALSE_WEIGHT = 0.7, 0.25, 0.5  # how query_utility counts


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


def check_two_grids(folders: list, card) -> None:
    """ParqError unless every scene of ``folders`` has frames with two point-sampling grids
    for ``card``'s network (scene.capture_grids)."""
    for folder in folders:
        if scene.capture_grids(card, readers.open_capture(folder)) < 2:
            w, h = card.image_size
            raise ParqError(f"{folder}: its frames have one point-sampling grid for this "
                            f"{w}x{h} model ({card.image_filter!r} filter); --phase-data "
                            f"needs frames at least twice its size each way")

