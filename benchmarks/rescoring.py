"""Learned rescoring of fused scene boxes: can a better keep rule than the card's support and
score threshold turn the model's reach into F1?

The error analysis (docs/demo-experiments.md) found that the detections overlap more objects
than the post-processing keeps: `--denoise 0.4` reaches 70% of the held-out objects at IoU 0.25
but scores F1 0.49.  The card keeps a fused box when enough runs support it and its best
detection scores above a threshold.  This script asks whether the statistics of each fused box's
cluster of detections tell the right boxes from the wrong ones better than that:

1. Runs the model once on the validation and the held-out scenes
   (``parq_train.validation_runs.run_once``, the card's run setting, mirror runs as the card
   says; every snippet box kept).
2. For each pre-fusion score threshold in --thresholds: fuses each scene (ray fusion, the card's
   ratio, no region, support 1), describes every cluster by :func:`features`, and labels it
   right when its fused box overlaps a ground-truth box of its class at IoU >= 0.25.
3. Fits an L2-regularised logistic regression (scipy's L-BFGS) on the validation clusters,
   chooses the probability cut by F1@0.25 + F1@0.5 on the validation scenes, and scores the
   held-out scenes with it, against the card's own rule on the same detections and against
   the oracle that keeps exactly the right clusters (the ceiling of any keep rule on them).

Paired differences on the held-out scenes are spread.py's bootstrap.  Writes
results/rescoring.{md,json} (--out).

    python benchmarks/rescoring.py --model models/parq-demo --scenes 120
    python benchmarks/rescoring.py --model work/dn4/model --scenes 120 --out work/dn4/rescoring
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

import common
import spread
import tradeoff
from parq_runtime import Detector, evaluation
from parq_runtime.iou import iou_matrix
from parq_train import postprocess_search as search, validation_runs

LABEL_IOU = 0.25
EVERYWHERE = (-np.inf, np.inf, -np.inf, np.inf)   # a region that keeps every box
CUTS = np.round(np.arange(0.2, 0.8, 0.025), 3)
FEATURES = ("log(1 + support)", "log(1 + members)", "log(1 + snippets)", "max score",
            "mean score", "log(score sum)", "share of members with the box's class",
            "share of score with the box's class", "relative size spread", "center spread (m)",
            "log volume (m^3)", "distance from the cameras (m)", "support / runs in the scene",
            "share of snippets detecting it in both runs", "a single member of its class")


def fuse(records: list, threshold: float, ray_ratio: float, mirror: bool) -> list:
    """Per scene: (SceneFusion of the snippet boxes scoring above ``threshold``, support 1,
    ray fusion, no region; truth; up; snippets)."""
    fused = search.fuse_records(records, threshold, EVERYWHERE, "ray", ray_ratio, mirror)
    return [(*scene, len(snippets)) for scene, (snippets, _, _) in zip(fused, records)]


def features(cluster, snippets: int, runs_per_snippet: int, classes: int) -> list:
    """FEATURES, then a one-hot of the fused box's class (``classes`` long), of one cluster of
    ``parq_runtime.fusion`` (its members are world-frame Boxes with viewpoints)."""
    box, members = cluster.fused, cluster.members
    scores = np.array([b.score for b in members])
    same = [b for b in members if b.label == box.label]
    sizes = np.stack([b.size for b in same])
    centers_world = np.stack([b.center for b in same])
    viewpoints_world = np.stack([b.viewpoint for b in same])
    seen_by = {run[0] for run in cluster.runs}
    both = sum((s, False, 0.0) in cluster.runs and (s, True, 0.0) in cluster.runs
               for s in seen_by)
    single = len(same) == 1
    row = [np.log1p(cluster.support), np.log1p(len(members)), np.log1p(len(seen_by)),
           scores.max(), scores.mean(), np.log(scores.sum()), len(same) / len(members),
           sum(b.score for b in same) / scores.sum(),
           0.0 if single else float((sizes.std(0) / sizes.mean(0)).mean()),
           0.0 if single else float(np.sqrt(((centers_world - box.center) ** 2).sum(1).mean())),
           float(np.log(np.prod(box.size))),
           float(np.linalg.norm(box.center - viewpoints_world.mean(0))),
           cluster.support / (runs_per_snippet * snippets), both / len(seen_by), float(single)]
    onehot = [0.0] * classes
    onehot[box.label] = 1.0
    return row + onehot


def dataset(fused: list, runs_per_snippet: int, classes: int) -> tuple:
    """(features (n, f), right (n,) bool, (scene, cluster) of each row) over the scenes."""
    rows, right, where = [], [], []
    for s, (fusion, truth, up, snippets) in enumerate(fused):
        for k, cluster in enumerate(fusion.clusters):
            rows.append(features(cluster, snippets, runs_per_snippet, classes))
            same = [t for t in truth if t.class_name == cluster.fused.class_name]
            right.append(bool(same) and iou_matrix([cluster.fused], same, up).max()
                         > LABEL_IOU)
            where.append((s, k))
    return np.array(rows), np.array(right), where


def fit(X: np.ndarray, y: np.ndarray, l2: float):
    """Logistic regression on standardised features; returns X -> probability."""
    mean, scale = X.mean(0), X.std(0) + 1e-9

    def design(X):
        return np.c_[(X - mean) / scale, np.ones(len(X))]

    Z, y = design(X), y.astype(float)

    def loss(w):
        z = Z @ w
        penalty = np.r_[w[:-1], 0.0]
        value = (np.logaddexp(0.0, z) - y * z).mean() + 0.5 * l2 * penalty @ penalty
        return value, Z.T @ (1.0 / (1.0 + np.exp(-z)) - y) / len(y) + l2 * penalty

    w = minimize(loss, np.zeros(Z.shape[1]), jac=True, method="L-BFGS-B").x
    return lambda X: 1.0 / (1.0 + np.exp(-(design(X) @ w)))


def auc(probability: np.ndarray, right: np.ndarray) -> float:
    """Area under the ROC curve: the chance that a right cluster outranks a wrong one (ties
    count half), how well the rule separates them whatever its cut."""
    ranks = np.empty(len(probability))
    order = np.argsort(probability, kind="stable")
    ranks[order] = np.arange(1, len(probability) + 1)
    for value in np.unique(probability):        # ties share their mean rank
        tied = probability == value
        ranks[tied] = ranks[tied].mean()
    positives = int(right.sum())
    negatives = len(right) - positives
    return float((ranks[right].sum() - positives * (positives + 1) / 2)
                 / max(positives * negatives, 1))


def kept_pairs(fused: list, where: list, keep, score=None) -> list:
    """(kept fused boxes, truth, up) per scene; ``keep`` a bool per row of :func:`dataset`,
    ``score`` (optional) the boxes' new scores, which order parq-eval's matching."""
    scenes = [[] for _ in fused]
    for row, (s, k) in enumerate(where):
        if keep[row]:
            box = fused[s][0].clusters[k].fused
            scenes[s].append(box if score is None else replace(box, score=float(score[row])))
    return [(boxes, truth, up) for boxes, (_, truth, up, _) in zip(scenes, fused)]


def f1s(pairs: list, classes) -> tuple:
    metrics = evaluation.evaluate(pairs, classes)
    return metrics["0.25"]["f1"], metrics["0.5"]["f1"]


def card_pairs(records: list, card, mirror: bool) -> list:
    """The card's own rule on the same detections: its threshold, region, ratio, support and
    scene NMS."""
    fused = search.fuse_records(records, card.score_threshold, card.eval_region, card.fusion,
                                card.ray_ratio, mirror, card.scene_nms)
    return [(fusion.boxes_with_support(card.min_support), truth, up)
            for fusion, truth, up in fused]


def losses(card_held: list, fused: list, where: list, right: np.ndarray) -> dict:
    """Where the card's rule loses F1 on the held-out scenes at IoU LABEL_IOU: its false boxes
    by kind (a second box on an object already found; one on an object of its class but
    overlapping it too little; one on an object of another class; one on no object), and
    the objects it misses by whether some right cluster (``right``, rows of :func:`dataset`)
    covers them, with that cluster's support."""
    kinds = dict.fromkeys(("true", "duplicate", "localisation", "class", "nothing"), 0)
    missed = {"no right cluster": 0, **{f"right cluster, support {n}": 0 for n in range(1, 5)}}
    for s, (boxes, truth, up) in enumerate(card_held):
        hit, found = evaluation.matches(boxes, truth, LABEL_IOU, up)
        for box, true in zip(boxes, hit):
            same = [g for g in truth if g.class_name == box.class_name]
            other = [g for g in truth if g.class_name != box.class_name]
            overlap = iou_matrix([box], same, up).max() if same else 0.0
            kind = ("true" if true else "duplicate" if overlap > LABEL_IOU
                    else "localisation" if overlap > 0 else "class"
                    if other and iou_matrix([box], other, up).max() > LABEL_IOU else "nothing")
            kinds[kind] += 1
        covering = [fused[s][0].clusters[k] for row, (scene, k) in enumerate(where)
                    if scene == s and right[row]]
        for g, was_found in zip(truth, found):
            if was_found:
                continue
            support = [c.support for c in covering if c.fused.class_name == g.class_name
                       and iou_matrix([c.fused], [g], up)[0, 0] > LABEL_IOU]
            key = f"right cluster, support {min(max(support), 4)}" if support \
                else "no right cluster"
            missed[key] += 1
    return {"boxes": kinds, "missed objects": missed}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    tradeoff.add_scene_arguments(p, "rescore")
    p.add_argument("--val", nargs="+", type=pathlib.Path,
                   default=[pathlib.Path("data/val"), pathlib.Path("data/val2")],
                   help="validation scene folders (parq-synth) to fit and choose on "
                        "(default data/val data/val2)")
    p.add_argument("--val-scenes", type=int, default=None,
                   help="the first this many scenes of each validation folder (default all)")
    p.add_argument("--thresholds", nargs="+", type=float, default=[0.5, 0.7],
                   help="pre-fusion score thresholds to try (default 0.5 0.7)")
    p.add_argument("--l2", type=float, default=1e-3,
                   help="L2 weight of the logistic regression (default 0.001)")
    p.add_argument("--out", type=pathlib.Path, default=common.RESULTS / "rescoring",
                   help="output stem: .md, .json (default results/rescoring)")
    args = p.parse_args()

    detector = Detector(args.model)
    card, classes = detector.card, detector.classes
    iters, queries = card.run_setting(None, None)
    mirror = card.run_mirror
    runs = 2 if mirror else 1
    start = time.perf_counter()
    folders = validation_runs.validation_folders(args.val, args.val_scenes)
    validation = validation_runs.run_once(detector, folders, iters, queries, mirror=mirror)
    scenes, _ = tradeoff.scenes_from_arguments(args)
    held_out = validation_runs.run_once(detector, scenes, iters, queries, mirror=mirror)
    collect_minutes = (time.perf_counter() - start) / 60

    rows = [("card's rule", f1s(card_pairs(validation, card, mirror), classes),
             card_pairs(held_out, card, mirror), None)]
    lost = {}
    for threshold in args.thresholds:
        fused_val = fuse(validation, threshold, card.ray_ratio, mirror)
        fused_held = fuse(held_out, threshold, card.ray_ratio, mirror)
        X_val, right_val, where_val = dataset(fused_val, runs, len(classes))
        X_held, right_held, where_held = dataset(fused_held, runs, len(classes))
        model = fit(X_val, right_val, args.l2)
        p_val, p_held = model(X_val), model(X_held)
        on_val = [f1s(kept_pairs(fused_val, where_val, p_val >= c, p_val), classes)
                  for c in CUTS]
        best = int(np.argmax([a + b for a, b in on_val]))
        cut = float(CUTS[best])
        rows.append((f"learned, threshold {threshold}, cut {cut}", on_val[best],
                     kept_pairs(fused_held, where_held, p_held >= cut, p_held),
                     {"clusters": len(right_held), "right": float(right_held.mean()),
                      "auc": auc(p_held, right_held)}))
        rows.append((f"oracle, threshold {threshold}", None,
                     kept_pairs(fused_held, where_held, right_held), None))
        lost[threshold] = losses(rows[0][2], fused_held, where_held, right_held)
        print(rows[-2][0], "done", flush=True)

    stats = spread.spread([spread.counts_of(pairs, classes) for _, _, pairs, _ in rows],
                          10000, 40)
    machine = common.machine()
    lines = [f"Learned rescoring of fused boxes, {args.model}: fitted on {len(validation)} "
             f"validation scenes ({', '.join(map(str, args.val))}), scored on "
             f"{tradeoff.held_out_text(args)}, "
             f"{iters} x {queries}{', mirror runs' if mirror else ''}; logistic regression "
             f"(L2 {args.l2}) on {len(FEATURES)} cluster statistics and the class; a cluster "
             f"is right when its box overlaps one of its class at IoU >= {LABEL_IOU}. "
             f"Collecting the detections took {collect_minutes:.1f} min on {machine['cpu']}.",
             "", "Held out: paired differences against the card's rule; ahead: share of "
             "10,000 resamples of the scenes in which the row beats it.", "",
             "| rule | validation F1@0.25 / F1@0.5 | held-out AUC | held-out F1@0.25 (90%) "
             "| vs card | held-out F1@0.5 (90%) | vs card |", "|---|---|---|---|---|---|---|"]
    for (name, val, _, info), st in zip(rows, stats):
        cells = spread.paired_cells(st)
        shown = f"{val[0]:.3f} / {val[1]:.3f}" if val else "-"
        area = f"{info['auc']:.3f}" if info else "-"
        lines.append(f"| {name} | {shown} | {area} | " + " | ".join(cells) + " |")
    lines += ["", f"Where the card's rule loses on the held-out scenes at IoU {LABEL_IOU}: its "
              "boxes by kind (false ones: a second box on an object already found, a box "
              "on an object of its class overlapping it too little, on an object of another "
              "class, on none), and the objects it misses by whether a right cluster of "
              "the pre-fusion threshold covers them (its support in runs, 4 meaning 4 or "
              "more).", ""]
    for threshold, found in lost.items():
        counts = {**found["boxes"], **found["missed objects"]}
        if threshold == next(iter(lost)):
            lines += ["| pre-fusion threshold | " + " | ".join(counts) + " |",
                      "|---|" + "---:|" * len(counts)]
        lines.append(f"| {threshold} | " + " | ".join(str(v) for v in counts.values()) + " |")
    common.write_report(args.out, lines, {"features": list(FEATURES), "losses": lost, "rows": [
        {"rule": name, "validation": val, "clusters": info, **st}
        for (name, val, _, info), st in zip(rows, stats)]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
