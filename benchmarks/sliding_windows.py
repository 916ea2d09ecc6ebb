"""Do overlapping snippets help? The demo run on sliding windows (parq-run --stride 1 or 2)
against its default, non-overlapping windows (stride 3 = views).

A sliding window makes about three times the snippets of a capture; each frame still goes
through ResNet-FPN once (parq_runtime.scene's feature cache), so a scene costs the loop and ray
encoding per extra snippet.  More snippets give each object more chances to be detected and
more detections to fuse, so the minimum support that suits them is higher: for each stride the
post-processing (score threshold x minimum support, ray fusion with the card's region and ratio
and one wider region and ratio 30) is chosen on the validation scenes (data/val, seed 2000,
F1@0.25 + F1@0.5, as parq_train.tune) and then applied to tradeoff.py's 40 held-out scenes.
Each stride runs the detector once per scene set (no threshold, no region); every candidate is
applied to those detections, as parq_train.tune does.  Writes results/sliding_windows.{md,json}.

    python benchmarks/sliding_windows.py [--model models/parq-demo] [--iters 2 --queries 32]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from multiprocessing import Pool

import common
from tradeoff import add_scene_arguments, held_out_text, scenes_from_arguments

STRIDES = (3, 2, 1)
SUPPORTS = (1, 2, 3, 4, 5, 6)
THRESHOLDS = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9)
WIDER_REGION, WIDER_RATIO = (-3.0, 3.0, 0.0, 4.5), 30.0

_records, _classes = None, None  # the records a worker scores (set by _share)


def _share(records, classes):
    global _records, _classes
    _records, _classes = records, classes


def _score(candidate) -> dict:
    from parq_train import postprocess_search as search

    threshold, support, region, ratio = candidate
    return search.candidate(_records, _classes, threshold, region, "ray", support, ratio)


def grid(records, classes, candidates, jobs: int) -> list:
    with Pool(jobs, initializer=_share, initargs=(records, classes)) as pool:
        return pool.map(_score, candidates, chunksize=4)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_arguments(p, "measure")
    p.add_argument("--val", type=pathlib.Path, default=pathlib.Path("data/val"),
                   help="validation scenes the post-processing is chosen on (default data/val)")
    p.add_argument("--iters", type=int, default=2, help="iterations (default 2)")
    p.add_argument("--queries", type=int, default=32, help="queries (default 32)")
    p.add_argument("--jobs", type=int, default=2, help="processes scoring the grid (default 2)")
    p.add_argument("--out", default=str(common.RESULTS / "sliding_windows"),
                   help="output stem: .md, .json (default results/sliding_windows)")
    args = p.parse_args()

    from parq_runtime import Detector
    from parq_train import postprocess_search as search, validation_runs

    det = Detector(args.model)
    post = det.card.raw["postprocess"]
    card_region, card_ratio = tuple(post["eval_region"]), float(post["ray_ratio"])
    held, _ = scenes_from_arguments(args)
    val = sorted(f.parent for f in args.val.glob("*/boxes.json"))
    candidates = [(t, s, region, ratio) for region, ratio in
                  ((card_region, card_ratio), (WIDER_REGION, WIDER_RATIO))
                  for s in SUPPORTS for t in THRESHOLDS]
    rows = []
    for stride in STRIDES:
        start = time.perf_counter()
        val_records = validation_runs.run_once(det, val, args.iters, args.queries, stride)
        held_records = validation_runs.run_once(det, held, args.iters, args.queries, stride)
        seconds = time.perf_counter() - start
        table = grid(val_records, det.classes, candidates, args.jobs)
        best = search.best_of(table)
        m = search.score(held_records, best["score_threshold"], best["eval_region"], det.classes,
                         "ray", best["min_support"], best["ray_ratio"])
        row = {"stride": stride,
               "snippets": {"val": sum(len(r[0]) for r in val_records),
                            "held_out": sum(len(r[0]) for r in held_records)},
               "detector_seconds": round(seconds, 1), "chosen_on_val": best,
               "held_out": {k: round(m[k]["f1"], 4) for k in m}}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    write(pathlib.Path(args.out), rows, args)


def write(out: pathlib.Path, rows: list, args) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(
        {"machine": common.machine(), "model": str(args.model), "iters": args.iters,
         "queries": args.queries, "rows": rows}, indent=1))
    lines = [f"{args.model}, {args.iters} iterations x {args.queries} queries, 3-view snippets; "
             f"post-processing chosen per stride on {args.val} (ray fusion), held-out = "
             f"{held_out_text(args)}.", "",
             "| stride | snippets (val / held-out) | chosen: threshold, support, region, ratio "
             "| val F1@0.25 / 0.5 | held-out F1@0.25 / 0.5 / 0.7 |",
             "|---:|---:|---|---:|---:|"]
    for r in rows:
        b, h = r["chosen_on_val"], r["held_out"]
        lines.append(f"| {r['stride']} | {r['snippets']['val']} / {r['snippets']['held_out']} "
                     f"| {b['score_threshold']}, {b['min_support']}, {b['eval_region']}, "
                     f"{b['ray_ratio']:g} | {b['f1@0.25']:.3f} / {b['f1@0.5']:.3f} | "
                     f"{h['0.25']:.3f} / {h['0.5']:.3f} / {h['0.7']:.3f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
