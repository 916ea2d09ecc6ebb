"""The class a scene box reports, and nearby changes to the scene fusion, on validation scenes.

Merging every class into one lifts the demo card's F1@0.25 on the 160 validation scenes from
0.573 to 0.585: what naming costs once boxes are found.  The fusion's matching does not
compare classes, so an object's cluster holds detections that call it different things, and
its best-scoring detection alone named it.  This script scores, each paired with the card
before the vote over 10,000 resamples of the scenes (spread.py):

* ``labels vote`` (parq_runtime.fusion; the demo card's now): the class whose detections' scores
  sum highest;
* ``labels vote, probabilities``: the class whose summed class probabilities (each detection's
  softmax over the classes, not only its argmax score) are highest;
* ``objectness T``: snippet detections scored by 1 - p(no object) instead of the top class's
  probability (a box whose probability is split between two classes is then kept), threshold
  T, labels by probability vote;
* ``class-agnostic NMS I``: scene NMS also across classes, at IoU I, the box with more
  support kept;
* ``matching IoU M``, ``gate G``: the matching's IoU floor (0.1) moved, or detections whose
  centers lie within G metres of a scene box's also matched to it.

Every variant keeps the rest of the card (its run setting with mirror runs, threshold 0.8, ray
fusion, support 4, scene NMS 0.1, the floor prior, found as parq-run finds it), and each row
also gives its F1 with every class merged.  Writes results/labels.{md,json} (--out).  Validation
scenes only: the variants were chosen on them.

    python benchmarks/labels.py --val data/val data/val2
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy.optimize import linear_sum_assignment

import common
import spread
from parq_train import postprocess_search as search, validation_runs


def objectness_logits(logits: np.ndarray) -> np.ndarray:
    """(K, classes + 1) logits whose softmax gives the top class all of the classes' mass:
    its probability is then 1 - p(no object), and the other classes' 0.  Decoded by
    parq_runtime.boxes.detections, boxes are scored by objectness with the same label."""
    logits = np.asarray(logits, dtype=np.float64)
    classes = logits[:, :-1]
    out = np.full_like(logits, -np.inf)
    top = classes.argmax(-1)
    out[np.arange(len(logits)), top] = np.logaddexp.reduce(classes, axis=-1)
    out[:, -1] = logits[:, -1]
    return out


def collect(detector, folders: list, iters: int, queries: int) -> list:
    """Per scene ([(snippet, mirrored, last Iteration, T_world_local)], truth, up): each
    snippet run plain and mirrored (the card's run setting), nothing filtered."""
    from parq_runtime import evaluation, mirror, readers

    records = []
    for folder in folders:
        capture = readers.open_capture(folder)
        runs = []
        for n, views in enumerate(common.snippet_views(capture, detector.card)):
            for mirrored in (False, True):
                inputs = mirror.mirror_snippet(*views, capture.up) if mirrored else views
                found = detector.detect(*inputs, iters=iters, queries=queries,
                                        score_threshold=0.0, region=False, up=capture.up)
                runs.append((n, mirrored, found.iterations[-1], found.T_world_local))
        truth, up = evaluation.load_ground_truth(folder / "boxes.json")
        records.append((runs, truth, up))
    return records


def decoded(records: list, detector, objectness: bool) -> list:
    """Per scene ([(snippet, mirrored, [(box with .probs (classes,), its local center)])],
    truth, up): the runs' boxes as common.run_boxes decodes them, each with the class
    probabilities of its query."""
    from parq_runtime import boxes as box_decoding

    out = []
    for runs, truth, up in records:
        scene = []
        for n, mirrored, last, T_world_local in runs:
            probs = box_decoding.softmax(np.asarray(last.logits, dtype=np.float64))
            if objectness:
                last = dataclasses.replace(last, logits=objectness_logits(last.logits))
            boxes = common.run_boxes(last, T_world_local, detector, up, mirrored)
            for b, _ in boxes:
                b.probs = probs[b.query, :-1]
            scene.append((n, mirrored, boxes))
        out.append((scene, truth, up))
    return out


def variant_fusion():
    """A SceneFusion subclass with the variants' knobs besides ``labels``: ``probs`` (label by
    summed class probabilities), ``agnostic`` (cross-class scene NMS IoU, or None) and
    ``gate`` (metres, or None)."""
    from parq_runtime.fusion import SceneFusion, _Cluster
    from parq_runtime.iou import iou_matrix

    class Variant(SceneFusion):
        probs, agnostic, gate = False, None, None

        def _summarise(self, cluster, floor=None):
            if not self.probs:
                return super()._summarise(cluster, floor)
            # the voted class's detections alone, summarised as the authors' rule would: its
            # best detection stands for them, and the mean or ray solve runs over them
            label = int(np.argmax(sum(b.probs for b in cluster.members)))
            keep = [i for i, b in enumerate(cluster.members) if b.label == label]
            view = _Cluster([cluster.members[i] for i in keep],
                            [cluster.runs[i] for i in keep]) if keep else cluster
            return super()._summarise(view, floor)

        def _match(self, detections):
            if self.gate is None or not self.clusters:
                return super()._match(detections)
            fused = [c.fused for c in self.clusters]
            gain = iou_matrix(detections, fused, self.up)
            gain = np.where(gain >= self.iou_threshold, gain, 0.0)
            # a pair under the IoU floor but within the gate: a small gain, nearer is more
            d = np.linalg.norm(np.stack([b.center for b in detections])[:, None]
                               - np.stack([f.center for f in fused])[None], axis=-1)
            gain = np.where((gain == 0) & (d < self.gate), 1e-3 * (1 - d / self.gate), gain)
            assigned = [-1] * len(detections)
            for r, c in zip(*linear_sum_assignment(-gain)):
                if gain[r, c] > 0:
                    assigned[r] = int(c)
            return assigned

        def _kept(self, min_support=None):
            kept = super()._kept(min_support)
            if self.agnostic is None or len(kept) < 2:
                return kept
            boxes = [c.fused for c in kept]
            overlap = iou_matrix(boxes, boxes, self.up)
            chosen = []
            for i in sorted(range(len(kept)), key=lambda i: (-kept[i].support, -boxes[i].score)):
                if not any(overlap[i, j] > self.agnostic for j in chosen):
                    chosen.append(i)
            return [kept[i] for i in sorted(chosen)]

    return Variant


BEST, VOTE = {"labels": "best"}, {"labels": "vote"}
VARIANTS = {   # name: (objectness, threshold, fusion knobs, matching IoU)
    "labels best (the card before)": (False, None, BEST, None),
    "labels vote (the card)": (False, None, VOTE, None),
    "labels vote, probabilities": (False, None, {**BEST, "probs": True}, None),
    "objectness 0.8": (True, 0.8, {**BEST, "probs": True}, None),
    "objectness 0.85": (True, 0.85, {**BEST, "probs": True}, None),
    "vote, class-agnostic NMS 0.3": (False, None, {**VOTE, "agnostic": 0.3}, None),
    "vote, class-agnostic NMS 0.2": (False, None, {**VOTE, "agnostic": 0.2}, None),
    "vote, matching IoU 0.05": (False, None, VOTE, 0.05),
    "vote, matching IoU 0.15": (False, None, VOTE, 0.15),
    "vote, gate 0.2 m": (False, None, {**VOTE, "gate": 0.2}, None),
    "vote, gate 0.5 m": (False, None, {**VOTE, "gate": 0.5}, None),
}


def fused_pairs(scenes: list, card, Variant, knobs: dict, threshold: float, match_iou,
                sweep) -> list:
    """(scene boxes, truth, up) per scene with the card's fusion and the variant's knobs."""
    from parq_runtime.fusion import MATCH_IOU

    region = card.eval_region
    fused = []
    for runs, truth, up in scenes:
        fusion = Variant(iou_threshold=MATCH_IOU if match_iou is None else match_iou, up=up,
                         mode=card.fusion, min_support=card.min_support,
                         ray_ratio=card.ray_ratio, scene_nms=card.scene_nms,
                         floor_classes=card.floor_classes, floor_weight=card.floor_weight)
        for key, value in knobs.items():
            setattr(fusion, key, value)
        for snippet, mirrored, boxes in runs:
            fusion.add(search.kept_boxes(boxes, threshold, region), snippet, mirrored)
        fused.append((fusion, truth, up))
    return search.floor_pairs(fused, card.min_support, card.floor_classes, card.floor_weight,
                              sweep)


def merged(pairs: list, classes) -> list:
    """``pairs`` with every prediction and ground-truth box of the first class."""
    def one(b):
        return dataclasses.replace(b, label=0, class_name=classes[0])
    return [([one(b) for b in boxes], [one(t) for t in truth], up)
            for boxes, truth, up in pairs]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.validation_arguments(p)
    p.add_argument("--out", default=str(common.RESULTS / "labels"),
                   help="output stem: .md and .json (default results/labels)")
    args = p.parse_args()
    detector, folders = common.open_validation(args, "labels")
    card = detector.card
    iters, queries = card.run_setting()
    start = time.perf_counter()
    records = collect(detector, folders, iters, queries)
    minutes = (time.perf_counter() - start) / 60
    print(f"collected {len(folders)} scenes in {minutes:.1f} min", flush=True)
    scenes = {False: decoded(records, detector, False), True: decoded(records, detector, True)}
    Variant, sweep = variant_fusion(), validation_runs.floor_sweep(folders)
    counts, rows = [], []
    for name, (objectness, threshold, knobs, match_iou) in VARIANTS.items():
        pairs = fused_pairs(scenes[objectness], card, Variant, knobs,
                            card.score_threshold if threshold is None else threshold,
                            match_iou, sweep)
        counts.append(spread.counts_of(pairs, detector.classes))
        one = spread.f1(spread.counts_of(merged(pairs, detector.classes),
                                         detector.classes).sum(axis=0))
        rows.append({"variant": name, "merged_f1": [float(v) for v in one]})
        print(name, np.round(spread.f1(counts[-1].sum(axis=0)), 4), "classes merged",
              np.round(one, 4), flush=True)
    stats = spread.spread(counts, 10000, 40)
    machine = common.machine()
    lines = [f"Scene boxes' classes and fusion variants, {args.model.name}, on {len(folders)} "
             f"validation scenes ({', '.join(map(str, args.val))}); {iters} x {queries}, "
             "mirror runs; paired against the first row (the card before the vote) over "
             f"10,000 resamples of the scenes; detection pass {minutes:.1f} min on "
             f"{machine['cpu']}, {machine['cores']} cores.", "",
             "| variant | F1@0.25 | vs first | F1@0.5 | vs first | F1@0.25 / 0.5, classes merged |",
             "|---|---|---|---|---|---|"]
    for row, s in zip(rows, stats):
        cells = spread.paired_cells(s)
        lines.append(f"| {row['variant']} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} "
                     f"| {row['merged_f1'][0]:.3f} / {row['merged_f1'][1]:.3f} |")
        row.update(spread=s)
    common.write_report(common.pathlib.Path(args.out), lines,
                        {"machine": machine, "scenes": len(folders), "iters": iters,
                         "queries": queries, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
