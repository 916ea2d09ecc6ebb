"""A probe: would a score threshold per class, instead of the card's one, raise held-out F1?

The card keeps the snippet detections scoring above one threshold (0.75 on the demo's card)
whatever their class.  The classes are not equally easy: small ones (trash bins, displays) are
the ones no detection reaches, large ones are found in nearly every snippet.  This script
chooses a threshold per class on the validation scenes and scores it on held-out ones,
paired against the card, with everything else the card's post-processing (region, ray
fusion, support, scene NMS, floor prior, label vote):

1. one detector pass over the validation scenes (data/val + data/val2, 160 scenes) at the
   card's run setting, as ``python -m parq_train.tune`` makes it; the card's own threshold on
   those records must give the card's tuned score (checked, printed);
2. coordinate ascent: two sweeps over the classes in the card's order, each class's threshold
   set to the value of parq_train.postprocess_search's THRESHOLDS that scores best with the
   others fixed, by the card's criterion (parq_train.postprocess_search.Criterion: best F1@0.25
   with F1@0.5 of at least 0.35, then F1@0.5; the current value wins ties);
3. one pass over the held-out scenes (seeds 3000 and 5000, 120 each, spread.py's cache), the
   card's threshold and the per-class ones scored on the same detections, the difference
   paired and bootstrapped as spread.py does.

It changes nothing the runtime does: parq-run has one threshold.  Writes
results/class-thresholds.{md,json} (--out).

    python benchmarks/class_thresholds.py models/parq-demo --seed 3000 5000 --scenes 120
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import common
import spread
import tradeoff


def keep_above(records: list, thresholds: dict, mirror: bool) -> list:
    """``records`` (parq_train.validation_runs.run_once's) with each snippet's boxes cut to those
    scoring above their class's threshold."""
    def kept(boxes):
        return [(b, c) for b, c in boxes if b.score > thresholds[b.class_name]]

    return [([(kept(s[0]), kept(s[1])) if mirror else kept(s) for s in snippets], truth, up)
            for snippets, truth, up in records]


def scene_pairs(records: list, thresholds: dict, post: dict, mirror: bool, sweep) -> list:
    """(scene boxes, truth, up) per scene: the card's post-processing ``post`` with the
    per-class ``thresholds`` in place of its one."""
    from parq_train import postprocess_search as search

    fused = search.fuse_records(keep_above(records, thresholds, mirror), -1.0,
                                post["eval_region"], post["fusion"], post["ray_ratio"], mirror,
                                post["scene_nms"], post["labels"])
    return search.floor_pairs(fused, post["min_support"], post["floor_classes"],
                              post["floor_weight"], sweep)


def f1s(pairs: list, classes) -> dict:
    """{"f1@0.25": F, "f1@0.5": F}, pooled over the scenes as parq-eval pools them (the keys
    parq_train.postprocess_search.Criterion ranks by)."""
    summed = spread.counts_of(pairs, classes).sum(axis=0)
    return {f"f1@{t}": float(v) for t, v in zip(spread.THRESHOLDS, spread.f1(summed))}


def ascend(records, classes, post, mirror, sweep, criterion, thresholds: dict, best: dict,
           sweeps: int = 2) -> tuple:
    """(per-class thresholds, their validation F1s, the trace) by coordinate ascent from
    ``thresholds``, which score ``best`` (module doc, step 2); ``criterion``: a
    parq_train.postprocess_search.Criterion."""
    from parq_train import postprocess_search as search

    trace = []
    for n in range(sweeps):
        for c in classes:
            for value in search.THRESHOLDS:
                if float(value) == thresholds[c]:
                    continue
                trial = dict(thresholds, **{c: float(value)})
                scores = f1s(scene_pairs(records, trial, post, mirror, sweep), classes)
                if criterion.key(scores) > criterion.key(best):
                    thresholds, best = trial, scores
            trace.append({"sweep": n + 1, "class": c, "threshold": thresholds[c], **best})
            print(f"sweep {n + 1} {c:>10}: {thresholds[c]:.2f}  F1@0.25 {best['f1@0.25']:.4f}"
                  f"  F1@0.5 {best['f1@0.5']:.4f}", file=sys.stderr, flush=True)
    return thresholds, best, trace


def markdown(result: dict, classes: list) -> str:
    """The results table of main's ``result``."""
    thresholds = result["thresholds"]
    iters, queries, mirror = result["setting"]
    lines = [f"Per-class score thresholds chosen on {result['validation_scenes']} validation "
             f"scenes, scored on {result['held_out']}; {result['model']} at {iters} x "
             f"{queries}{', mirror runs' if mirror else ''}, the rest its card's "
             "post-processing (benchmarks/class_thresholds.py).", "",
             "| class | " + " | ".join(classes) + " |",
             "|---|" + "---|" * len(classes),
             "| threshold | " + " | ".join(f"{thresholds[c]:.2f}" for c in classes) + " |", "",
             "| thresholds | validation F1@0.25 / F1@0.5 | held out F1@0.25 | paired "
             "| held out F1@0.5 | paired |", "|---|---|---|---|---|---|"]
    for name, key, row in zip(("the card's one", "per class"), ("card", "per_class"),
                              result["held_out_rows"]):
        val = result["validation"][key]
        lines.append(f"| {name} | {val['f1@0.25']:.4f} / {val['f1@0.5']:.4f} | "
                     + " | ".join(spread.paired_cells(row)) + " |")
    return "\n".join(lines) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("model", help="model folder whose card's post-processing is the baseline")
    p.add_argument("--validation", type=pathlib.Path, nargs="+",
                   default=[common.ROOT / "data" / "val", common.ROOT / "data" / "val2"],
                   help="validation scene folders (default data/val data/val2)")
    p.add_argument("--validation-scenes", type=int, default=None,
                   help="the first N scenes of each validation folder (default all)")
    p.add_argument("--min-f1-50", type=float, default=0.35,
                   help="the criterion's floor on validation F1@0.5 (default 0.35, the card's)")
    tradeoff.add_scene_arguments(p, "score", model=False)
    p.add_argument("--resamples", type=int, default=10000,
                   help="bootstrap resamples of the held-out scenes (default 10000)")
    p.add_argument("--out", default=str(common.RESULTS / "class-thresholds"),
                   help="output stem: .md and .json (default results/class-thresholds)")
    args = p.parse_args()

    from parq_runtime import Detector
    from parq_train import postprocess_search as search, validation_runs

    detector = Detector(args.model)
    card, classes = detector.card, list(detector.classes)
    post = card.raw["postprocess"]
    iters, queries = card.run_setting(None, None)
    mirror = card.run_mirror
    start = time.perf_counter()

    folders = validation_runs.validation_folders(args.validation, args.validation_scenes)
    records = validation_runs.run_once(detector, folders, iters, queries, mirror=mirror)
    sweep = validation_runs.floor_sweep(folders)
    card_thresholds = {c: float(post["score_threshold"]) for c in classes}
    card_val = f1s(scene_pairs(records, card_thresholds, post, mirror, sweep), classes)
    print(f"validation, {len(folders)} scenes, the card's threshold: F1@0.25 "
          f"{card_val['f1@0.25']:.4f}  F1@0.5 {card_val['f1@0.5']:.4f}", file=sys.stderr,
          flush=True)
    criterion = search.Criterion(args.min_f1_50)
    thresholds, chosen_val, trace = ascend(records, classes, post, mirror, sweep, criterion,
                                           card_thresholds, card_val)

    scenes, _ = tradeoff.scenes_from_arguments(args)
    held = validation_runs.run_once(detector, scenes, iters, queries, mirror=mirror)
    held_sweep = validation_runs.floor_sweep(scenes)
    counts = [spread.counts_of(scene_pairs(held, t, post, mirror, held_sweep), classes)
              for t in (card_thresholds, thresholds)]
    rows = spread.spread(counts, args.resamples, block=40)

    result = {"model": args.model, "setting": [iters, queries, mirror],
              "validation_scenes": len(folders), "held_out": tradeoff.held_out_text(args),
              "card_threshold": float(post["score_threshold"]), "thresholds": thresholds,
              "validation": {"card": card_val, "per_class": chosen_val}, "trace": trace,
              "held_out_rows": rows, "minutes": (time.perf_counter() - start) / 60}
    text = markdown(result, classes)
    out = pathlib.Path(args.out)
    out.with_suffix(".md").write_text(text)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    print(text, end="")


if __name__ == "__main__":
    main()
