"""The demo's own layer as a verifier of its scene boxes: every candidate box is queried again,
as a reference point at its center, in every snippet that sees it.  Chosen and scored on
validation scenes only (nothing here was kept, so the held-out scenes were not spent on it).

The oracle keep rule of ``rescoring.py`` shows the F1 left in telling right scene boxes from
wrong ones, and the statistics of a box's detections do not carry it.  What a snippet's
learned queries miss, a query started at the box might see: the paper's 0.2 m proximity
matching trains a query whose reference point lies near an object's center to call it that
object, and every iteration after the first starts from wherever the one before put its
query.  So the network could say, snippet by snippet, whether there is an object of the
box's class at the box, including in the snippets whose learned queries did not find it.

Each validation scene is run as parq-run runs it (the card's setting, mirror runs, fusion and
floor).  Its candidates are all its scene boxes down to support 1.  Every snippet (plain and
mirrored) then runs the layer again from the candidates whose centers lie inside its decoder
box and project into one of its views: ``alone`` (only those points) and ``with`` (appended to
the card's learned queries, which they can attend to).  A candidate's verification score is
the mean, over those runs, of the probability of its own class after iteration 1 or 2.

Printed and written: how well each score separates the candidates that overlap an object of
their class at IoU 0.25 (ROC AUC, beside the support and score that the card's rule uses),
each variant's best keep rule (verification mean >= t and support >= s, chosen on these same
scenes, so an upper bound) paired against the card's post-processing over 10,000 resamples of
the scenes (spread.py), and the centre error of the verified centers against the fused ones.
Writes results/requery.{md,json} (--out).

    python benchmarks/requery.py --val data/val data/val2
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np
from scipy.stats import rankdata

import common
import spread

VARIANTS = (("alone", 1), ("alone", 2), ("with", 1), ("with", 2))
MEANS = tuple(np.round(np.arange(0.1, 0.95, 0.05), 2))
SUPPORTS = (1, 2, 3, 4)


def visible(points_local, camera, T_camera_local, feature_size) -> np.ndarray:
    """(M,) bool: the local points that project inside the feature image of some view, in
    front of its camera (camera (N, 4) pinholes at feature resolution)."""
    from parq_runtime import geometry

    points_camera = np.stack([geometry.transform(T, points_local) for T in T_camera_local])
    _, valid = geometry.project(points_camera, camera[:, None, :], feature_size, eps=0.1)
    return valid.any(0)


def requery(detector, images, K, T_world_camera, centers_world, up, learned) -> tuple:
    """(indices of the candidates queried, {(variant, iteration): (probabilities (M, C+1),
    centers (M, 3) world)}) for one snippet run."""
    from parq_runtime import geometry, loop
    from parq_runtime.boxes import softmax

    card = detector.card
    images, camera, T_world_local, T_local_camera = detector.prepare(images, K,
                                                                     T_world_camera, up)
    T_camera_local = geometry.invert(T_local_camera)
    points_local = geometry.transform(geometry.invert(T_world_local), centers_world)
    normalised = loop.normalize(points_local, card.decoder_scale)
    chosen = np.flatnonzero(np.all((normalised > 0.02) & (normalised < 0.98), -1)
                            & visible(points_local, camera, T_camera_local, card.feature_size))
    out = {}
    if len(chosen) == 0:
        return chosen, out
    factors, operands = detector.encode(images, camera, T_local_camera, True)
    ref = normalised[chosen].astype(np.float32)
    for variant, points, tail in (("alone", ref, slice(0, None)),
                                  ("with", np.concatenate([learned, ref]), slice(len(learned),
                                                                               None))):
        iterations = loop.run(detector.layer, factors, operands, camera, T_camera_local,
                              points.astype(np.float32), 2, card.decoder_scale, True)
        for k, it in enumerate(iterations):
            prob = softmax(np.asarray(it.logits, dtype=np.float64))[tail]
            center = geometry.transform(T_world_local, np.asarray(it.center, np.float64)[tail])
            out[variant, k + 1] = (prob, center)
    return chosen, out


def collect(detector, folders: list) -> list:
    """Per scene: candidates (boxes, supports), the card's boxes, truth, up, and per
    candidate and variant the verification probabilities of its class and verified centers."""
    from parq_runtime import evaluation, mirror, readers, scene

    card = detector.card
    learned = detector.reference_points(card.run_setting()[1])
    records = []
    for folder in folders:
        capture = readers.open_capture(folder)
        result = scene.run(detector, capture, scene.RunSettings())
        fusion = result.fusion
        card_boxes = fusion.boxes
        fusion.min_support = 1
        boxes, supports = fusion.boxes, fusion.supports
        centers = np.array([b.center for b in boxes], dtype=np.float64).reshape(-1, 3)
        labels = np.array([b.label for b in boxes], dtype=np.int64)
        verified = {v: ([[] for _ in boxes], [[] for _ in boxes]) for v in VARIANTS}
        M = mirror.world_reflection(capture.up)
        for images, K, T_world_camera in common.snippet_views(capture, card) if boxes else []:
            plain = requery(detector, images, K, T_world_camera, centers, capture.up, learned)
            chosen, out = requery(detector, *mirror.mirror_snippet(images, K, T_world_camera,
                                                                   capture.up),
                                  centers @ M.T, capture.up, learned)
            reflected = (chosen, {k: (p, c @ M.T) for k, (p, c) in out.items()})
            for chosen, out in (plain, reflected):
                for key, (prob, center) in out.items():
                    for j, c in enumerate(chosen):
                        verified[key][0][c].append(prob[j, labels[c]])
                        verified[key][1][c].append(center[j])
        truth, up = evaluation.load_ground_truth(folder / "boxes.json")
        records.append({"boxes": boxes, "supports": np.array(supports), "card": card_boxes,
                        "truth": truth, "up": up,
                        "mean": {k: np.array([np.mean(p) if p else 0.0 for p in v[0]])
                                 for k, v in verified.items()},
                        "centers": {k: [np.mean(c, 0) if c else None for c in v[1]]
                                    for k, v in verified.items()}})
    return records


def correct(record, threshold: float = 0.25) -> np.ndarray:
    """(C,) bool: candidates overlapping a ground-truth box of their class above threshold."""
    from parq_runtime.iou import iou_matrix

    boxes, truth = record["boxes"], record["truth"]
    if not boxes or not truth:
        return np.zeros(len(boxes), dtype=bool)
    same = np.array([[b.class_name == g.class_name for g in truth] for b in boxes])
    return ((iou_matrix(boxes, truth, record["up"]) > threshold) & same).any(1)


def auc(scores, positive) -> float:
    """ROC AUC (Mann-Whitney, ties at half)."""
    ranks = rankdata(scores)
    n1, n0 = positive.sum(), (~positive).sum()
    return float((ranks[positive].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def centre_errors(records: list, support: int) -> dict:
    """Median distance to the matched object's center (IoU >= 0.1, same class) of the
    candidates at the card's ``support``, fused against verified (mean of the verified
    centers)."""
    from parq_runtime.iou import iou_matrix

    errors = {"fused": []} | {f"{v} {k}": [] for v, k in VARIANTS}
    for r in records:
        if not r["boxes"] or not r["truth"]:
            continue
        iou = iou_matrix(r["boxes"], r["truth"], r["up"])
        for c, box in enumerate(r["boxes"]):
            j = int(np.argmax(iou[c]))
            verified = [r["centers"][key][c] for key in VARIANTS]
            if iou[c, j] < 0.1 or r["truth"][j].class_name != box.class_name \
                    or r["supports"][c] < support or any(v is None for v in verified):
                continue
            errors["fused"].append(np.linalg.norm(box.center - r["truth"][j].center))
            for (v, k), center in zip(VARIANTS, verified):
                errors[f"{v} {k}"].append(np.linalg.norm(center - r["truth"][j].center))
    return {k: {"median": round(float(np.median(e)), 3), "n": len(e)} for k, e in errors.items()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.validation_arguments(p)
    p.add_argument("--out", type=pathlib.Path, default=common.HERE / "results" / "requery")
    args = p.parse_args()

    detector, folders = common.open_validation(args, "requery")
    start = time.perf_counter()
    records = collect(detector, folders)
    minutes = (time.perf_counter() - start) / 60
    print(f"collected {len(folders)} scenes in {minutes:.1f} min", flush=True)
    classes = detector.classes
    positive = np.concatenate([correct(r) for r in records])
    supports = np.concatenate([r["supports"] for r in records])
    scores = np.concatenate([[b.score for b in r["boxes"]] for r in records])
    aucs = {"support": auc(supports, positive), "score": auc(scores, positive),
            "support + score": auc(supports + scores, positive)}
    baseline = spread.counts_of([(r["card"], r["truth"], r["up"]) for r in records], classes)
    rows, counts = [], []
    for key in VARIANTS:
        mean = np.concatenate([r["mean"][key] for r in records])
        aucs[f"{key[0]} {key[1]}"] = auc(mean, positive)
        aucs[f"{key[0]} {key[1]} + support / 8"] = auc(mean + supports / 8, positive)
        best = None
        for t in MEANS:
            for s in SUPPORTS:
                kept = [([b for b, m, n in zip(r["boxes"], r["mean"][key], r["supports"])
                          if m >= t and n >= s], r["truth"], r["up"]) for r in records]
                c = spread.counts_of(kept, classes)
                f = spread.f1(c.sum(axis=0))
                if best is None or (f.sum(), f[1]) > (best[0].sum(), best[0][1]):
                    best = (f, float(t), s, c)
        rows.append({"variant": key[0], "iteration": key[1], "mean_at_least": best[1],
                     "support_at_least": best[2]})
        counts.append(best[3])
        print(rows[-1], np.round(best[0], 3), flush=True)
    stats = spread.spread([baseline] + counts, 10000, 40)
    errors = centre_errors(records, detector.card.min_support)
    machine = common.machine()
    card = detector.card
    lines = [f"Re-querying scene boxes, {args.model.name}, on {len(folders)} validation scenes "
             f"({', '.join(map(str, args.val))}), the card's setting {card.run_setting()} with "
             f"mirror runs; {len(positive)} candidates (support >= 1), {int(positive.sum())} "
             f"right at IoU 0.25; machine: {machine['cpu']}, {machine['cores']} cores; "
             f"collected in {minutes:.1f} min.", "",
             "How well each score separates right candidates from wrong ones (ROC AUC):", "",
             "| score | AUC |", "|---|---:|"]
    lines += [f"| {k} | {v:.3f} |" for k, v in aucs.items()]
    lines += ["", "Best keep rule of each variant (verification mean >= t and support >= s, "
              "chosen on these same scenes: upper bounds), paired against the card's "
              "post-processing (first row):", "",
              "| keep rule | F1@0.25 (90%) | vs card | F1@0.5 (90%) | vs card |",
              "|---|---|---|---|---|",
              "| the card | " + " | ".join(spread.paired_cells(stats[0])) + " |"]
    for row, st in zip(rows, stats[1:]):
        lines.append(f"| {row['variant']}, iteration {row['iteration']}: mean >= "
                     f"{row['mean_at_least']}, support >= {row['support_at_least']} | "
                     + " | ".join(spread.paired_cells(st)) + " |")
    lines += ["", "Median centre error of the candidates at the card's support that overlap an "
              "object of their class (IoU >= 0.1): "
              + "; ".join(f"{k} {v['median']} m" for k, v in errors.items())
              + f" (n = {errors['fused']['n']})."]
    common.write_report(args.out, lines, {"scenes": len(folders), "aucs": aucs, "rows": rows,
                                          "stats": stats, "centre_errors": errors,
                                          "minutes": minutes})
    return 0


if __name__ == "__main__":
    sys.exit(main())
