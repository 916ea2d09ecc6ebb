"""Where the demo model's F1 is lost: classes, localisation, or objects the capture barely shows.

On the held-out scenes of tradeoff.py (parq-synth seed 3000), at each --settings (iterations x
queries), every scene runs once with no score threshold and no region (as parq_train.tune
does), and from those detections:

* **F1** as parq-eval scores it with the model's post-processing, and again with every class
  merged into one (predictions and ground truth): the difference is what classification costs;
* **reach**: the share of ground-truth boxes that some detection of some snippet overlaps at
  IoU 0.25 / 0.5, whatever its score, region or class, before fusion. It bounds the recall
  any post-processing of these detections could give;
* **recall through the post-processing**: reach at IoU 0.25 of every detection, of those above
  the score threshold, then recall and precision of the fused scene boxes with support 1 and
  with the card's minimum support (parq-eval's numbers);
* reach by **visibility**: an object's instance-mask pixels (parq-synth's instance/ masks) in
  the snippet that shows most of it, summed over the snippet's views, out of views x W x H;
* **F1 over seen objects**: scored against the ground-truth boxes some snippet shows (at least
  --seen pixels). ScanNet's boxes are annotated on the reconstructed mesh, so an object that
  no frame saw has no box there; parq-synth's boxes.json lists every object in the room.
  parq-eval and the README's headline numbers count every object.
* **centre errors along and across the viewing ray**: each detection with a ground-truth box
  of its class within 1 m has its centre error split into the part along the ray from the
  snippet's camera (depth) and the part across it; F1 is scored again with each part removed
  (the detection moved by it, nothing else changed), and with the centre exact. What F1 gains
  from removing a part is what that part costs.

It analyses each snippet's plain run: no mirror runs, and a card chosen with them has its
support scaled to one run a snippet, as parq-run --no-mirror does (:func:`support_of`).

    python benchmarks/error_analysis.py [--model models/parq-demo] [--scenes 40]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import numpy as np

import common
from tradeoff import add_scene_arguments, held_out_text, scenes_from_arguments

VISIBILITY_BINS = (0, 1, 200, 800, 3000)     # pixel-count bins' lower edges
IOUS = (0.25, 0.5)


def instance_pixels(folder: pathlib.Path, frame_names: list, count: int,
                    masks: dict) -> np.ndarray:
    """(count,) pixels of each ground-truth box summed over the frames' instance masks
    (value 1 + j marks boxes[j]); ``masks`` caches the masks read."""
    import cv2

    total = np.zeros(count)
    for name in frame_names:
        if name not in masks:
            mask = cv2.imread(str(folder / "instance" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
            if mask is None:
                sys.exit(f"error_analysis: {folder / 'instance' / f'{name}.png'}: no instance "
                         f"mask (scenes must come from parq-synth)")
            masks[name] = np.bincount(mask.ravel(), minlength=count + 1)[1:count + 1]
        total += masks[name]
    return total


def run_scene(detector, folder: pathlib.Path, iters: int, queries: int) -> dict:
    """One scene's raw snippet detections (with local centers, for postprocess_search.score), its
    truth and, per ground-truth box, the best IoU any detection reaches and its visibility."""
    from parq_runtime import evaluation, geometry, readers, scene
    from parq_runtime.iou import iou_matrix

    settings = scene.RunSettings(iters=iters, queries=queries, score_threshold=0.0,
                                 region=False, mirror=False)
    result = scene.run(detector, readers.open_capture(folder), settings)
    truth, up = evaluation.load_ground_truth(folder / "boxes.json")
    reach, visible, masks, snippets = np.zeros(len(truth)), np.zeros(len(truth)), {}, []
    poses = []                                   # T_world_local of each snippet
    for s in result.snippets:
        T_local_world = geometry.invert(s.T_world_local)
        snippets.append([(b, geometry.transform(T_local_world, b.center)) for b in s.boxes])
        poses.append(s.T_world_local)
        if s.boxes and truth:
            reach = np.maximum(reach, iou_matrix(s.boxes, truth, up).max(0))
        visible = np.maximum(visible, instance_pixels(folder, s.frames, len(truth), masks))
    return {"snippets": snippets, "truth": truth, "up": up, "reach": reach, "visible": visible,
            "poses": poses}


def support_of(card) -> int:
    """The card's minimum support for plain runs, as parq-run --no-mirror uses it."""
    from parq_runtime import scene

    return scene.min_support(scene.RunSettings(mirror=False), card)


def one_class(box):
    return dataclasses.replace(box, label=0, class_name="object")


def scores(scenes: list, card, classes, seen: float) -> dict:
    """F1 (as parq-eval), class-agnostic, and over seen objects only, at the card's
    post-processing."""
    from parq_train import postprocess_search as search

    def f1(records, names):
        m = search.score(records, card.score_threshold, card.eval_region, names, card.fusion,
                         support_of(card), card.ray_ratio, scene_nms=card.scene_nms)
        return {t: {k: round(m[t][k], 4) for k in ("precision", "recall", "f1")} for t in m}

    every = [(s["snippets"], s["truth"], s["up"]) for s in scenes]
    merged = [([[(one_class(b), c) for b, c in snippet] for snippet in s["snippets"]],
               [one_class(b) for b in s["truth"]], s["up"]) for s in scenes]
    shown = [(s["snippets"], [b for b, v in zip(s["truth"], s["visible"]) if v >= seen],
              s["up"]) for s in scenes]
    return {"every object": f1(every, classes), "classes merged": f1(merged, ["object"]),
            "seen objects": f1(shown, classes)}


def stages(scenes: list, card, classes) -> dict:
    """Recall at IoU 0.25 (and precision, once fused) through the post-processing steps."""
    from parq_runtime.iou import iou_matrix
    from parq_train import postprocess_search as search

    truth = sum(len(s["truth"]) for s in scenes)
    above = 0
    for s in scenes:
        reach = np.zeros(len(s["truth"]))
        for snippet in s["snippets"]:
            kept = [b for b, _ in snippet if b.score > card.score_threshold]
            if kept and s["truth"]:
                reach = np.maximum(reach, iou_matrix(kept, s["truth"], s["up"]).max(0))
        above += int((reach >= IOUS[0]).sum())
    records = [(s["snippets"], s["truth"], s["up"]) for s in scenes]
    out = {"any score": {"recall": round(float(np.mean(np.concatenate(
               [s["reach"] for s in scenes]) >= IOUS[0])), 4)},
           f"score > {card.score_threshold}": {"recall": round(above / max(truth, 1), 4)}}
    for support in sorted({1, support_of(card)}):
        m = search.score(records, card.score_threshold, card.eval_region, classes, card.fusion,
                         support, card.ray_ratio, scene_nms=card.scene_nms)[str(IOUS[0])]
        out[f"fused ({card.fusion}), support {support}"] = {
            k: round(m[k], 4) for k in ("recall", "precision")}
    return out


RAY_FIXES = ("as run", "along-ray error removed", "across-ray error removed", "centre exact")


def ray_errors(scenes: list, card, classes, radius: float = 1.0) -> dict:
    """Centre errors along / across the viewing ray and F1 with each removed (module doc).

    The ray runs from the snippet frame's origin (its middle view's camera centre, world) to
    the detection's centre; a detection is matched to the nearest ground-truth centre of its
    class within ``radius`` metres, and unmatched ones stay as they are."""
    from parq_runtime import geometry
    from parq_train import postprocess_search as search

    records = {fix: [] for fix in RAY_FIXES}
    along, across = [], []
    for s in scenes:
        truth_centers = np.array([t.center for t in s["truth"]]).reshape(-1, 3)
        truth_labels = np.array([t.label for t in s["truth"]])
        fixed = {fix: [] for fix in RAY_FIXES}
        for snippet, T_world_local in zip(s["snippets"], s["poses"]):
            origin, R_world_local = T_world_local[:3, 3], T_world_local[:3, :3]
            per_fix = {fix: [] for fix in RAY_FIXES}
            for box, center_local in snippet:
                center = np.asarray(box.center, dtype=np.float64)
                moved = {fix: center for fix in RAY_FIXES}
                same = np.flatnonzero(truth_labels == box.label)
                if len(same):
                    j = same[np.argmin(np.linalg.norm(truth_centers[same] - center, axis=1))]
                    error = center - truth_centers[j]
                    if np.linalg.norm(error) < radius:
                        ray = geometry.unit(center - origin)
                        error_along = ray * (ray @ error)
                        if box.score > card.score_threshold:
                            along.append(abs(ray @ error))
                            across.append(np.linalg.norm(error - error_along))
                        moved = {"as run": center, "along-ray error removed": center - error_along,
                                 "across-ray error removed": center - (error - error_along),
                                 "centre exact": truth_centers[j]}
                for fix, c in moved.items():
                    shift = c - center                                   # world frame
                    per_fix[fix].append((dataclasses.replace(box, center=c,
                                                             corners=box.corners + shift),
                                         center_local + shift @ R_world_local))
            for fix in RAY_FIXES:
                fixed[fix].append(per_fix[fix])
        for fix in RAY_FIXES:
            records[fix].append((fixed[fix], s["truth"], s["up"]))
    f1 = {}
    for fix in RAY_FIXES:
        m = search.score(records[fix], card.score_threshold, card.eval_region, classes,
                         card.fusion, support_of(card), card.ray_ratio, scene_nms=card.scene_nms)
        f1[fix] = {t: round(m[t]["f1"], 4) for t in m}
    return {"matched": len(along), "median_along": round(float(np.median(along)), 4) if along
            else None, "median_across": round(float(np.median(across)), 4) if across else None,
            "f1": f1}


def reach_table(scenes: list, classes) -> dict:
    """Share of ground-truth boxes reached at each IoU, overall, by visibility bin, by class."""
    reach = np.concatenate([s["reach"] for s in scenes])
    visible = np.concatenate([s["visible"] for s in scenes])
    labels = np.array([b.class_name for s in scenes for b in s["truth"]])

    def row(sel):
        return {"objects": int(sel.sum()),
                **{f"reach@{t}": round(float((reach[sel] >= t).mean()), 3) if sel.any() else None
                   for t in IOUS}}

    edges = VISIBILITY_BINS + (np.inf,)
    return {"all": row(np.ones(len(reach), bool)),
            "by_visibility": {f"[{lo}, {hi})": row((visible >= lo) & (visible < hi))
                              for lo, hi in zip(edges[:-1], edges[1:])},
            "by_class": {c: row(labels == c) for c in classes if (labels == c).any()}}


def markdown(results: list, args, pixels: int) -> str:
    lines = [f"{held_out_text(args)}, "
             f"3-view snippets; visibility out of {pixels} pixels per snippet.", "",
             "| iterations x queries | scored against | F1@0.25 | F1@0.5 | recall@0.25 | "
             "precision@0.25 |", "|---|---|---:|---:|---:|---:|"]
    for r in results:
        for name, m in r["f1"].items():
            lines.append(f"| {r['setting']} | {name} | {m['0.25']['f1']:.3f} | "
                         f"{m['0.5']['f1']:.3f} | {m['0.25']['recall']:.3f} | "
                         f"{m['0.25']['precision']:.3f} |")
    lines += ["", "Recall at IoU 0.25 through the post-processing (reach: some snippet "
              "detection overlaps the object):", "",
              "| step | " + " | ".join(f"recall ({r['setting']}) | precision ({r['setting']})"
                                     for r in results) + " |",
              "|---|" + "---:|---:|" * len(results)]
    for step in results[0]["stages"]:
        cells = []
        for r in results:
            m = r["stages"][step]
            cells += [f"{m['recall']:.3f}",
                      f"{m['precision']:.3f}" if "precision" in m else "-"]
        lines.append(f"| {step} | " + " | ".join(cells) + " |")
    lines += ["", "Reach: share of ground-truth boxes that some snippet detection (any score) "
              "overlaps at the IoU.", "",
              "| objects | n | " + " | ".join(f"reach@{t} ({r['setting']})" for r in results
                                              for t in IOUS) + " |",
              "|---|---:|" + "---:|" * (len(results) * len(IOUS))]
    first = results[0]["reach"]
    groups = [("all", lambda r: r["all"])] \
        + [(f"visibility {k} px", lambda r, k=k: r["by_visibility"][k])
           for k in first["by_visibility"]] \
        + [(k, lambda r, k=k: r["by_class"][k]) for k in first["by_class"]]
    for label, entry in groups:
        cells = ["-" if entry(r["reach"])[f"reach@{t}"] is None
                 else f"{entry(r['reach'])[f'reach@{t}']:.2f}" for r in results for t in IOUS]
        lines.append(f"| {label} | {entry(first)['objects']} | " + " | ".join(cells) + " |")
    lines += ["", "Centre errors of the detections above the score threshold that have a "
              "ground-truth box of their class within 1 m, split along and across the ray from "
              "the snippet's camera: " + "; ".join(
                  f"{r['setting']}: {r['ray']['matched']} detections, median along "
                  f"{r['ray']['median_along']} m, across {r['ray']['median_across']} m"
                  for r in results) + ". F1 with each part removed (the rest unchanged):", "",
              "| centre | " + " | ".join(f"F1@{t} ({r['setting']})" for r in results
                                       for t in IOUS) + " |",
              "|---|" + "---:|" * (len(results) * len(IOUS))]
    for fix in RAY_FIXES:
        lines.append(f"| {fix} | " + " | ".join(f"{r['ray']['f1'][fix][str(t)]:.3f}"
                                                for r in results for t in IOUS) + " |")
    return "\n".join(lines) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_arguments(p, "analyse")
    p.add_argument("--settings", default="2x32,8x64",
                   help="comma-separated iterations x queries (default 2x32,8x64: parq-run's "
                        "defaults and the best of the trade-off table)")
    p.add_argument("--seen", type=float, default=1,
                   help="pixels (summed over a snippet's views) from which an object counts as "
                        "seen (default 1)")
    p.add_argument("--out", default=str(common.RESULTS / "error_analysis"),
                   help="output stem: .md, .json (default results/error_analysis)")
    args = p.parse_args()

    from parq_runtime import Detector

    detector = Detector(args.model)
    folders, size = scenes_from_arguments(args)
    results = []
    for setting in args.settings.split(","):
        iters, queries = (int(v) for v in setting.split("x"))
        scenes = [run_scene(detector, f, iters, queries) for f in folders]
        results.append({"setting": setting, "f1": scores(scenes, detector.card,
                                                         detector.classes, args.seen),
                        "stages": stages(scenes, detector.card, detector.classes),
                        "reach": reach_table(scenes, detector.classes),
                        "ray": ray_errors(scenes, detector.card, detector.classes)})
        print(json.dumps(results[-1]["f1"]), file=sys.stderr, flush=True)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(
        {"model": args.model, "scenes": args.scenes, "seed": args.seed, "seen": args.seen,
         "results": results}, indent=1))
    text = markdown(results, args, 3 * size[0] * size[1])
    out.with_suffix(".md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
