"""How much of a difference in held-out F1 is noise: bootstrap intervals over the scenes.

tradeoff.py's F1 pools 40 held-out scenes; another 40 (other seeds, a user's own) give another
number, so a model that scores 0.02 above another on them may not be better.  This script runs
each model folder at one setting on the held-out scenes (parq-synth seed 3000, the same cache as
tradeoff.py), keeps every scene's match counts, and resamples the scenes with replacement
(--resamples times, a fixed seed) to print

* each model's scene-level F1 at IoU 0.25 and 0.5, with a 90% interval;
* each later model's difference from the first, *paired*: both scored on the same resampled
  scenes, so what the scenes share (an easy room, a hidden bin) cancels; with the fraction of
  resamples in which the later model is ahead;
* the F1 of each disjoint block of --block scenes: the spread between held-out sets of that
  size, without resampling.

Writes results/spread.{md,json} (--out).  F1 here is parq-eval's, pooled over scenes:
2 TP / (predictions + ground truth), which is 2PR / (P + R).

A model may name its own setting, MODEL:ITERSxQUERIES, to compare settings of one model the
same way (the default is --iters x --queries where given, else the model card's run setting,
what parq-run runs by default; the table names each entry's setting), and end in :mirror or
:no-mirror to add or leave out mirror runs (default: the card's run setting):

    python benchmarks/spread.py models/parq-demo work/s1/model --scenes 120
    python benchmarks/spread.py models/parq-demo:1x32 models/parq-demo:4x32 --scenes 120
    python benchmarks/spread.py models/parq-demo:no-mirror models/parq-demo --scenes 120

--seen-only scores against the boxes some frame of each capture shows, as parq-eval
--seen-only does (ScanNet's ground truth holds only what its scan saw; parq-synth's lists every
object in the room); the held-out cache must then have been generated with that record:

    python benchmarks/spread.py models/parq-demo models/parq-demo:4x64 models/parq-demo:1x64 \
        --scenes 120 --seen-only --out benchmarks/results/spread-seen-only

--baseline FILE.json:ENTRY makes the first row an entry of an earlier run's .json instead of a
new run, so that runs on the same rooms rendered at another --size are paired (same scene
count and the same ground-truth boxes per scene, checked; its setting comes with it):

    python benchmarks/spread.py models/parq-demo --scenes 120 --size 320x240 \
        --baseline benchmarks/results/spread-goal-criterion.json:work/parq-demo-goal \
        --out benchmarks/results/spread-320-goal
"""
from __future__ import annotations

import argparse
import json
import pathlib
import re
import sys

import numpy as np

import common
import tradeoff

THRESHOLDS = ("0.25", "0.5")


def scene_counts(detector, scenes: list, iters: int, queries: int,
                 mirror: bool | None = None, seen_only: bool = False) -> np.ndarray:
    """(scenes, thresholds, 3) int: each scene's (true positives, predictions, ground-truth
    boxes), pooled over classes, at the model card's post-processing (``mirror`` None: and
    its mirror runs; ``seen_only``: against the boxes some frame shows)."""
    pairs, _ = tradeoff.run_scenes(detector, scenes, iters, queries, mirror=mirror,
                                   seen_only=seen_only)
    return counts_of(pairs, detector.classes)


def counts_of(pairs: list, classes) -> np.ndarray:
    """(scenes, thresholds, 3) int counts, as scene_counts, of (scene boxes, truth, up) per
    scene."""
    from parq_runtime import evaluation

    counts = np.zeros((len(pairs), len(THRESHOLDS), 3), dtype=np.int64)
    for s, (boxes, truth, up) in enumerate(pairs):
        for t, threshold in enumerate(THRESHOLDS):
            per_class = evaluation.match_counts(boxes, truth, float(threshold), classes, up)
            counts[s, t] = [sum(n[k] for n in per_class.values())
                            for k in ("tp", "predictions", "ground_truth")]
    return counts


def truth_counts(scenes: list, classes, seen_only: bool = False) -> np.ndarray:
    """(scenes, thresholds) int: the ground-truth boxes each scene is scored against, as
    :func:`counts_of` counts them, without running a model."""
    from parq_runtime import evaluation

    pairs = [([], *evaluation.load_ground_truth(folder / "boxes.json", seen_only))
             for folder in scenes]
    return counts_of(pairs, classes)[..., 2]


def f1(summed: np.ndarray) -> np.ndarray:
    """F1 from (..., 3) summed counts."""
    denominator = summed[..., 1] + summed[..., 2]
    return np.where(denominator > 0, 2 * summed[..., 0] / np.maximum(denominator, 1), 0.0)


def spread(counts: list, resamples: int, block: int, seed: int = 0) -> dict:
    """counts: one (scenes, thresholds, 3) array per model, the same scenes in the same order.
    Returns per model and threshold: F1, its 90% bootstrap interval, the block F1s, and for
    models after the first the paired difference from the first."""
    n = counts[0].shape[0]
    index = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    boot = [f1(c[index].sum(axis=1)) for c in counts]            # (resamples, thresholds)
    out = []
    for m, c in enumerate(counts):
        row = {}
        for t, name in enumerate(THRESHOLDS):
            blocks = [float(f1(c[b:b + block, t].sum(axis=0)))
                      for b in range(0, n - block + 1, block)]
            entry = {"f1": float(f1(c[:, t].sum(axis=0))),
                     "interval90": [float(v) for v in np.percentile(boot[m][:, t], [5, 95])],
                     "blocks": blocks}
            if m > 0:
                d = boot[m][:, t] - boot[0][:, t]
                entry["difference"] = entry["f1"] - float(f1(counts[0][:, t].sum(axis=0)))
                entry["difference_interval90"] = [float(v) for v in np.percentile(d, [5, 95])]
                entry["ahead"] = float((d > 0).mean())
            row[name] = entry
        out.append(row)
    return out


def paired_cells(row: dict) -> list:
    """Table cells of one model's :func:`spread` row: per threshold, "F1 (90% interval)" and,
    for models after the first, "difference (its interval), ahead N%"."""
    cells = []
    for t in THRESHOLDS:
        e = row[t]
        cells.append(f"{e['f1']:.3f} ({e['interval90'][0]:.3f}-{e['interval90'][1]:.3f})")
        cells.append(f"{e['difference']:+.3f} ({e['difference_interval90'][0]:+.3f} to "
                     f"{e['difference_interval90'][1]:+.3f}), ahead {e['ahead']:.0%}"
                     if "difference" in e else "")
    return cells


def markdown(models: list, settings: list, rows: list, args) -> str:
    lines = [f"{tradeoff.held_out_text(args)}, each model's card post-processing, at the "
             f"setting (iterations x queries) in its row; 90% intervals from {args.resamples} "
             f"resamples of the scenes; blocks: F1 of each run of {args.block} scenes."
             + (" Ground truth: only the boxes some frame of the capture shows "
                "(parq-eval --seen-only)." if args.seen_only else ""), ""]
    head = "| model | setting | " + " | ".join(
        f"F1@{t} | 90% interval | blocks of {args.block} | vs first, paired | ahead"
        for t in THRESHOLDS) + " |"
    lines += [head, "|---" * (2 + 5 * len(THRESHOLDS)) + "|"]
    for model, (iters, queries, mirror), row in zip(models, settings, rows):
        cells = [model, f"{iters} x {queries}" + (", mirror runs" if mirror else "")]
        for t in THRESHOLDS:
            e = row[t]
            lo, hi = e["interval90"]
            cells += [f"{e['f1']:.3f}", f"{lo:.3f}-{hi:.3f}",
                      " ".join(f"{b:.2f}" for b in e["blocks"])]
            if "difference" in e:
                dlo, dhi = e["difference_interval90"]
                cells += [f"{e['difference']:+.3f} ({dlo:+.3f} to {dhi:+.3f})",
                          f"{e['ahead']:.0%}"]
            else:
                cells += ["", ""]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def saved_counts(spec: str, scenes: int, seen_only: bool) -> tuple:
    """'FILE.json:ENTRY' -> (label, (iters, queries, mirror), (scenes, thresholds, 3) counts)
    of an earlier run of this script, checked to be on ``scenes`` scenes scored the same way."""
    path, _, entry = spec.partition(".json:")
    path = pathlib.Path(path + ".json")
    try:
        saved = json.loads(path.read_text())
        counts = np.asarray(saved["scene_counts"][entry], dtype=np.int64)
        setting = saved["settings"][saved["models"].index(entry)]
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"spread: --baseline {spec}: not an entry of a spread.py result "
                         f"({e})")
    if counts.shape != (scenes, len(THRESHOLDS), 3) or saved["seen_only"] != seen_only:
        raise SystemExit(f"spread: --baseline {spec}: {saved['scenes']} scenes, seen-only "
                         f"{saved['seen_only']}, not {scenes} and {seen_only}")
    label = f"{entry} ({path.name}, {saved['size']})"
    return label, (setting["iters"], setting["queries"], setting["mirror"]), counts


def parse_entry(entry: str, iters: int | None, queries: int | None) -> tuple:
    """'MODEL[:ITERSxQUERIES][:mirror|:no-mirror]' -> (model folder, iterations, queries,
    mirror runs); without a setting, ``iters`` and ``queries``, without a mirror suffix None
    (None: the model card's run setting)."""
    mirror = None
    model, _, suffix = entry.rpartition(":")
    if model and suffix in ("mirror", "no-mirror"):
        entry, mirror = model, suffix == "mirror"
    model, _, setting = entry.rpartition(":")
    if model and re.fullmatch(r"\d+x\d+", setting):
        i, q = setting.split("x")
        return model, int(i), int(q), mirror
    return entry, iters, queries, mirror


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+",
                   help="model folders, each optionally :ITERSxQUERIES (e.g. "
                        "models/parq-demo:4x32); the first is the baseline")
    tradeoff.add_scene_arguments(p, "score", model=False)
    p.add_argument("--iters", type=int, default=None,
                   help="recurrent iterations of models without their own setting (default: "
                        "each model card's run setting)")
    p.add_argument("--queries", type=int, default=None,
                   help="queries of models without their own setting (default: each model "
                        "card's run setting)")
    p.add_argument("--resamples", type=int, default=10000,
                   help="bootstrap resamples of the scenes (default 10000)")
    p.add_argument("--block", type=int, default=40,
                   help="scenes per disjoint block (default 40, tradeoff.py's count)")
    p.add_argument("--seen-only", action="store_true",
                   help="score against the ground-truth boxes some frame of the capture shows "
                        "(parq-eval --seen-only) instead of every box in the room")
    p.add_argument("--threads", type=int, default=None,
                   help="onnxruntime threads (default: its own choice)")
    p.add_argument("--baseline", default=None, metavar="FILE.json:ENTRY",
                   help="first row: ENTRY's scene counts from an earlier run's .json (e.g. "
                        "the same rooms at another --size) instead of a new run")
    p.add_argument("--out", default=str(common.RESULTS / "spread"),
                   help="output stem: .md and .json (default results/spread)")
    args = p.parse_args()
    if len(set(args.models)) < len(args.models):
        p.error("a model (and setting) is given twice")

    from parq_runtime import Detector

    scenes, _ = tradeoff.scenes_from_arguments(args)
    labels, detectors, counts, settings = list(args.models), {}, [], []
    if args.baseline:
        label, setting, saved = saved_counts(args.baseline, len(scenes), args.seen_only)
        first = parse_entry(args.models[0], args.iters, args.queries)[0]
        detectors[first] = Detector(first, threads=args.threads)
        if not np.array_equal(truth_counts(scenes, detectors[first].classes, args.seen_only),
                              saved[..., 2]):
            raise SystemExit(f"spread: --baseline {args.baseline}: its scenes hold other "
                             "ground-truth boxes than these")
        labels.insert(0, label)
        settings.append(setting)
        counts.append(saved)
    for entry in args.models:
        model, iters, queries, mirror = parse_entry(entry, args.iters, args.queries)
        if model not in detectors:
            detectors[model] = Detector(model, threads=args.threads)
        iters, queries = detectors[model].card.run_setting(iters, queries)
        mirror = detectors[model].card.run_mirror if mirror is None else mirror
        settings.append((iters, queries, mirror))
        counts.append(scene_counts(detectors[model], scenes, iters, queries, mirror,
                                   args.seen_only))
        print(f"{entry}: " + "  ".join(
            f"F1@{t} {float(f1(counts[-1][:, i].sum(axis=0))):.3f}"
            for i, t in enumerate(THRESHOLDS)), file=sys.stderr, flush=True)
    rows = spread(counts, args.resamples, args.block)
    out = pathlib.Path(args.out)
    text = markdown(labels, settings, rows, args)
    out.with_suffix(".md").write_text(text)
    out.with_suffix(".json").write_text(json.dumps(
        {"scenes": len(scenes), "seed": args.seed, "size": args.size,
         "resamples": args.resamples,
         "seen_only": args.seen_only,
         "block": args.block, "models": labels, "baseline": args.baseline,
         "settings": [{"iters": i, "queries": q, "mirror": m} for i, q, m in settings],
         "rows": rows,
         "scene_counts": {m: c.tolist() for m, c in zip(labels, counts)}}, indent=1))
    print(text)


if __name__ == "__main__":
    main()
