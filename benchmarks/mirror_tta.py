"""Mirror test-time augmentation (``parq-run --mirror``): what running each snippet also on its
mirror image buys, chosen on validation scenes and scored on held-out ones.

1. *Validation*: runs the model once on each validation scene with mirror runs (every snippet
   box kept: threshold 0, no region; ``parq_train.validation_runs.run_once``), then fuses the
   plain and the mirrored detections under a grid of post-processings (score threshold x ray
   ratio x minimum support, support counting runs; the card's evaluation region) and prints the
   best by F1@0.25 + F1@0.5, beside the card's own post-processing without mirror runs, fused
   from the same detections.  The grid is the card's neighbourhood (ray fusion only, one region; 40
   candidates), the question this script was written to answer before the card had mirror runs;
   the full grid is ``python -m parq_train.tune MODEL --mirror``, which made the demo's card.
2. *Held out*: ``parq-run``'s own pipeline (``scene.run``) on the held-out scenes (parq-synth
   seed 3000, tradeoff.py's cache) with the card's post-processing and no mirror, then with
   ``--mirror`` and the threshold, ratio and support the validation chose, at --settings,
   with spread.py's paired bootstrap (each entry against the first row).

Writes results/mirror_tta.{md,json} (--out).

    python benchmarks/mirror_tta.py --val data/val data/val2 --scenes 120
    python benchmarks/mirror_tta.py --val data/val data/val2 --scenes 40 --size 320x240 \
        --settings 2x64 --out benchmarks/results/mirror_tta-320
"""
from __future__ import annotations

import argparse
import itertools
import pathlib
import sys
import time

import numpy as np

import common
import spread
import tradeoff
from parq_train import postprocess_search as search, validation_runs

THRESHOLDS = (0.7, 0.75, 0.8, 0.85, 0.9)
RATIOS = (10.0, 30.0)
SUPPORTS = (1, 2, 3, 4)


def f1s(records: list, classes, threshold: float, region, ratio: float, support: int,
        mirror: bool) -> tuple:
    """(F1@0.25, F1@0.5) of ``records`` (validation_runs.run_once's with mirror runs) fused as
    parq-run fuses them with ray fusion and these settings, with or without the mirror runs."""
    if not mirror:
        records = [([plain for plain, _ in snippets], truth, up)
                   for snippets, truth, up in records]
    m = search.score(records, threshold, region, classes, "ray", support, ratio, mirror)
    return round(m["0.25"]["f1"], 4), round(m["0.5"]["f1"], 4)


def held_out(detector, scenes: list, iters: int, queries: int, chosen: dict | None) -> tuple:
    """(counts, seconds per snippet) of parq-run's pipeline on the held-out scenes: the card's
    post-processing without mirror runs (``chosen`` None; parq-run --no-mirror), else
    ``--mirror`` with the chosen threshold, ray ratio and support."""
    overrides = {"mirror": False} if chosen is None else {
        "mirror": True, **{k: chosen[k] for k in ("score_threshold", "ray_ratio", "min_support")}}
    pairs, seconds = tradeoff.run_scenes(detector, scenes, iters, queries, **overrides)
    return spread.counts_of(pairs, detector.classes), float(np.median(seconds))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=pathlib.Path, default=common.ROOT / "models" / "parq-demo")
    p.add_argument("--val", type=pathlib.Path, nargs="+", required=True,
                   help="validation folders of scenes (data/val data/val2)")
    p.add_argument("--scenes", type=int, default=120, help="held-out scenes (seed 3000)")
    p.add_argument("--size", default="160x120",
                   help="held-out frame size WxH (160x120, the model's; 320x240, parq-synth's "
                        "default, which parq-run resizes)")
    p.add_argument("--settings", nargs="+", default=["2x64", "1x64", "4x64"],
                   help="ITERSxQUERIES run with --mirror on the held-out scenes")
    p.add_argument("--out", type=pathlib.Path, default=common.HERE / "results" / "mirror_tta")
    args = p.parse_args()

    from parq_runtime import Detector

    detector = Detector(args.model)
    card = detector.card
    iters, queries = card.run_setting()
    folders = validation_runs.validation_folders(args.val, None)
    start = time.perf_counter()
    records = validation_runs.run_once(detector, folders, iters, queries, mirror=True)
    collect_minutes = (time.perf_counter() - start) / 60
    from parq_runtime import scene

    base = f1s(records, detector.classes, card.score_threshold, card.eval_region,
               card.ray_ratio, scene.min_support(scene.RunSettings(mirror=False), card), False)
    grid = []
    for t, q, s in itertools.product(THRESHOLDS, RATIOS, SUPPORTS):
        grid.append({"score_threshold": t, "ray_ratio": q, "min_support": s,
                     "f1": f1s(records, detector.classes, t, card.eval_region, q, s, True)})
    best = max(grid, key=lambda g: (sum(g["f1"]), g["f1"][1]))
    print(f"validation ({len(folders)} scenes, {iters} x {queries}): card without mirror "
          f"{base}; best with mirror {best}", flush=True)

    size = tuple(int(v) for v in args.size.split("x"))
    scenes = tradeoff.held_out_scenes(args.scenes, 60, size)
    rows = [(f"{iters} x {queries}, card, no mirror",
             *held_out(detector, scenes, iters, queries, None))]
    for entry in args.settings:
        i, q = (int(v) for v in entry.split("x"))
        rows.append((f"{i} x {q}, --mirror", *held_out(detector, scenes, i, q, best)))
        print(rows[-1][0], "done", flush=True)
    stats = spread.spread([r[1] for r in rows], 10000, 40)
    machine = common.machine()

    lines = [f"Mirror test-time augmentation, {args.model.name}: validation {len(folders)} "
             f"scenes ({', '.join(map(str, args.val))}), held-out {args.scenes} scenes "
             f"(parq-synth seed 3000, {args.size}); machine: {machine['cpu']}, {machine['cores']} "
             f"cores.", "",
             f"Validation at {iters} x {queries}, the card's post-processing without mirror "
             f"runs: F1 {base[0]:.3f} / {base[1]:.3f}. Best of the grid with mirror runs "
             f"(threshold {THRESHOLDS}, ray ratio {RATIOS}, support {SUPPORTS}; the card's "
             f"region): threshold {best['score_threshold']}, ratio {best['ray_ratio']}, "
             f"support {best['min_support']}: "
             f"F1 {best['f1'][0]:.3f} / {best['f1'][1]:.3f}. (Collecting the detections took "
             f"{collect_minutes:.1f} min.)", "",
             "Held out: parq-run's pipeline; the mirror rows run with the threshold, ratio and "
             "support chosen above. Paired differences against the first row; ahead: share of "
             "10,000 resamples in which the row beats it.", "",
             "| setting | ms a snippet (median) | F1@0.25 (90%) | vs first | F1@0.5 (90%) "
             "| vs first |", "|---|---:|---|---|---|---|"]
    for (name, _, sec), st in zip(rows, stats):
        cells = spread.paired_cells(st)
        lines.append(f"| {name} | {1000 * sec:.1f} | " + " | ".join(cells) + " |")
    common.write_report(args.out, lines, {
        "validation": {"scenes": len(folders), "card_without_mirror": base, "best": best,
                       "grid": grid},
        "held_out": [{"setting": name, "ms_per_snippet": 1000 * sec, **st}
                     for (name, _, sec), st in zip(rows, stats)]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
