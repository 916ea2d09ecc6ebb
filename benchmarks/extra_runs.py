"""More runs of each snippet for the scene fusion to vote on: the earlier iterations of a longer
run, zoomed centre crops, and another view as the local frame.  Chosen and scored on
validation scenes only (nothing here was kept, so the held-out scenes were not spent on it).

Mirror runs (parq_runtime.mirror) added a second, different look at every snippet and gained
+0.015 / +0.047; the demo's gap to F1@0.25 0.6 is in reach (docs/demo-experiments.md), so this
asks whether more looks of other kinds add more.  Each validation scene is run once, every
snippet plain and mirrored, keeping every box (threshold 0, no region):

* ``iterations``: one 4-iteration run each way, its boxes decoded after every iteration (the
  boxes of iteration k are those of a k-iteration run: the loop does not look ahead);
* ``crop C``: a run each way at the card's iterations on each view's centre crop of C of its
  width and height (intrinsics shifted with it, resized to the network size as any frame is):
  a narrower camera, 1/C the pixels on what it keeps.  Training drew focal lengths within
  +-10%; a crop of 0.85 is 1.18x;
* ``reference R``: a run each way at the card's iterations with the views reordered so that
  view R, not the middle one, is the snippet's local frame (the view order matters only
  there): the learned queries then start from other places in the room, and the boxes' depth
  is along another camera's rays.

Then sets of these runs are fused as parq-run fuses the card's two (ray fusion, the card's
ratio, region, scene NMS and floor prior, the floor found in the images), support counting
runs, for each score threshold and support of a small grid.  Printed and written: each set's
best row by F1@0.25 + F1@0.5, and its paired difference from the card's own setting (2
iterations, plain + mirrored, the card's threshold and support) over 10,000 resamples of the
scenes (spread.py).  Writes results/extra_runs.{md,json} (--out).

    python benchmarks/extra_runs.py --val data/val data/val2
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

import common
import spread
from parq_train import postprocess_search as search, validation_runs

THRESHOLDS = (0.75, 0.8, 0.85)
ITERATIONS = 4     # the run whose every iteration is kept; the other runs use the card's


def centre_crop(images: list, K: np.ndarray, fraction: float) -> tuple:
    """Each view's centre crop of ``fraction`` of its width and height, with its intrinsics
    (N, 3, 3) moved to the crop's pixel grid (the principal point shifts; the focal length in
    pixels stays, so the crop is a narrower camera)."""
    out, K = [], np.array(K, dtype=np.float64)
    for i, image in enumerate(images):
        H, W = image.shape[:2]
        w, h = int(round(W * fraction)), int(round(H * fraction))
        x0, y0 = (W - w) // 2, (H - h) // 2
        out.append(np.ascontiguousarray(image[y0:y0 + h, x0:x0 + w]))
        K[i, 0, 2] -= x0
        K[i, 1, 2] -= y0
    return out, K


def reference_order(views: int, reference: int) -> list:
    """The views' order that makes view ``reference`` the snippet's local frame (the view at
    geometry.local_view, the middle one), the others kept in their order."""
    from parq_runtime import geometry

    others = [i for i in range(views) if i != reference]
    middle = geometry.local_view(views)
    return others[:middle] + [reference] + others[middle:]


def looks(crops: tuple, references: tuple, iters: int) -> list:
    """(kind, iterations, views -> views) of each run of a snippet that collect() makes; kind
    None is the ITERATIONS run whose every iteration is kept, the others run ``iters``."""
    out = [(None, ITERATIONS, lambda images, K, T: (images, K, T))]
    for c in crops:
        out.append((("crop", c), iters,
                    lambda images, K, T, c=c: (*centre_crop(images, K, c), T)))
    for r in references:
        def reorder(images, K, T, r=r):
            order = reference_order(len(images), r)
            return [images[i] for i in order], K[order], T[order]
        out.append((("reference", r), iters, reorder))
    return out


def collect(detector, folders: list, crops: tuple, references: tuple, iters: int,
            queries: int) -> tuple:
    """(records, seconds): per scene (snippets, truth, up), a snippet a dict {(kind, mirrored):
    [(box, its local center)]} with kind an iteration number, ("crop", C) or ("reference", R);
    seconds: per kind of run, the median time of a snippet's two runs (plain and mirrored)."""
    from parq_runtime import evaluation, mirror, readers

    records, seconds = [], {}
    for folder in folders:
        capture = readers.open_capture(folder)
        runs_of_scene = []
        for images, K, T_world_camera in common.snippet_views(capture, detector.card):
            runs = {}
            for kind, run_iters, views_of in looks(crops, references, iters):
                views = views_of(images, K, T_world_camera)
                start = time.perf_counter()
                for mirrored in (False, True):
                    inputs = mirror.mirror_snippet(*views, capture.up) if mirrored else views
                    found = detector.detect(*inputs, iters=run_iters, queries=queries,
                                            score_threshold=0.0, region=False, up=capture.up)
                    # every iteration's boxes for kind None, else the last's
                    decoded = [common.run_boxes(it, found.T_world_local, detector, capture.up,
                                                mirrored)
                               for it in (found.iterations if kind is None
                                          else found.iterations[-1:])]
                    if kind is None:
                        for k, boxes in enumerate(decoded):
                            runs[k + 1, mirrored] = boxes
                    else:
                        runs[kind, mirrored] = decoded[-1]
                key = f"{run_iters} iterations" + (
                    "" if kind is None else f", {kind[0]} {kind[1]}")
                seconds.setdefault(key, []).append(time.perf_counter() - start)
            runs_of_scene.append(runs)
        truth, up = evaluation.load_ground_truth(folder / "boxes.json")
        records.append((runs_of_scene, truth, up))
    return records, {k: float(np.median(v)) for k, v in seconds.items()}


def fuse(records: list, kinds: list, card, threshold: float) -> list:
    """Per scene, a SceneFusion (support 1) of the runs ``kinds`` (each plain and mirrored) of
    every snippet, boxes above ``threshold`` in the card's region, with the card's fusion, and
    its floor found as parq-run finds it when a support is applied
    (postprocess_search.floor_pairs)."""
    from parq_runtime.fusion import SceneFusion

    region = card.eval_region
    fused = []
    for snippets, truth, up in records:
        fusion = SceneFusion(up=up, mode=card.fusion, ray_ratio=card.ray_ratio,
                             scene_nms=card.scene_nms, floor_classes=card.floor_classes,
                             floor_weight=card.floor_weight)
        for n, runs in enumerate(snippets):
            for j, key in enumerate((kind, m) for kind in kinds for m in (False, True)):
                # one run id per (snippet, run): support counts runs, as with mirror runs
                fusion.add(search.kept_boxes(runs[key], threshold, region),
                           n * 2 * len(kinds) + j)
        fused.append((fusion, truth, up))
    return fused


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.validation_arguments(p)
    p.add_argument("--crops", type=float, nargs="*", default=[0.85, 0.7],
                   help="centre-crop fractions to try as extra runs")
    p.add_argument("--references", type=int, nargs="*", default=[0, 2],
                   help="views to try as the snippet's local frame in extra runs (the card's "
                        "is the middle one)")
    p.add_argument("--out", type=pathlib.Path, default=common.HERE / "results" / "extra_runs")
    args = p.parse_args()

    detector, folders = common.open_validation(args, "extra_runs")
    card = detector.card
    iters, queries = card.run_setting()
    start = time.perf_counter()
    records, seconds = collect(detector, folders, tuple(args.crops),
                               tuple(args.references), iters, queries)
    print(f"collected {len(folders)} scenes in {(time.perf_counter() - start) / 60:.1f} min",
          flush=True)
    sweep = validation_runs.floor_sweep(folders)
    base_support = card.min_support
    sets = {f"{iters} iterations (the card)": [iters], "4 iterations": [4],
            "iterations 2 + 4": [2, 4], "iterations 2 + 3 + 4": [2, 3, 4],
            "iterations 1 + 2 + 3 + 4": [1, 2, 3, 4]}
    for c in args.crops:
        sets[f"crop {c}"] = [("crop", c)]
        sets[f"{iters} iterations + crop {c}"] = [iters, ("crop", c)]
    for r in args.references:
        sets[f"reference view {r}"] = [("reference", r)]
    if args.references:
        sets[f"{iters} iterations + reference views {args.references}"] = [iters] + [
            ("reference", r) for r in args.references]
    rows, counts = [], []
    def pairs(fused, support):    # the floor found near the kept boxes, as parq-run does
        return search.floor_pairs(fused, support, card.floor_classes, card.floor_weight, sweep)

    baseline = spread.counts_of(pairs(fuse(records, [iters], card, card.score_threshold),
                                      base_support), detector.classes)
    for name, kinds in sets.items():
        runs = 2 * len(kinds)
        supports = range(runs, 2 * runs + 1)   # the card's: 4 of its 2 runs
        best = None
        for threshold in THRESHOLDS:
            fused = fuse(records, kinds, card, threshold)
            for support in supports:
                c = spread.counts_of(pairs(fused, support), detector.classes)
                f = spread.f1(c.sum(axis=0))
                if best is None or (f.sum(), f[1]) > (best[0].sum(), best[0][1]):
                    best = (f, threshold, support, c)
        rows.append({"runs": name, "runs_per_snippet": runs, "score_threshold": best[1],
                     "min_support": best[2]})
        counts.append(best[3])
        print(name, rows[-1], np.round(best[0], 3), flush=True)
    stats = spread.spread([baseline] + counts, 10000, 40)
    machine = common.machine()
    lines = [f"Extra runs per snippet, {args.model.name}, on {len(folders)} validation scenes "
             f"({', '.join(map(str, args.val))}); {queries} queries; machine: "
             f"{machine['cpu']}, {machine['cores']} cores.", "",
             "Each row: its best score threshold and support (of thresholds "
             f"{THRESHOLDS}, supports from its runs to twice them), chosen on these same "
             "scenes, so the rows are upper bounds; paired against the card's own "
             "post-processing at "
             f"{iters} iterations (first row; support {base_support}).", "",
             "| runs of each snippet (each plain + mirrored) | runs | threshold | support "
             "| F1@0.25 (90%) | vs card | F1@0.5 (90%) | vs card |",
             "|---|---:|---:|---:|---|---|---|---|",
             f"| the card: {iters} iterations | 2 | {card.score_threshold} | {base_support} | "
             + " | ".join(spread.paired_cells(stats[0])) + " |"]
    for row, st in zip(rows, stats[1:]):
        lines.append(f"| {row['runs']} | {row['runs_per_snippet']} | {row['score_threshold']} "
                     f"| {row['min_support']} | " + " | ".join(spread.paired_cells(st)) + " |")
    lines += ["", "Median seconds of a snippet's two runs (plain + mirrored), this machine: "
              + "; ".join(f"{k} {v:.3f} s" for k, v in seconds.items()) + "."]
    common.write_report(args.out, lines, {"scenes": len(folders), "rows": rows,
                                          "stats": stats, "seconds": seconds})
    return 0


if __name__ == "__main__":
    sys.exit(main())
