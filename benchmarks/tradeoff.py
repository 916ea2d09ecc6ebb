"""Accuracy and latency as compute changes: the demo model on held-out generated scenes.

Generates --scenes scenes with parq-synth seed 3000 (training used seed 1000, validation 2000
and 2001, so no scene is shared; --seed picks another held-out set), runs parq-run's pipeline
(keyframes, 3-view snippets, scene fusion) at iterations 1, 2, 4, 8 x queries 16, 32, 64, 128
and the learned count, and reports scene-level F1 at IoU 0.25 / 0.5 / 0.7 (parq-eval's
protocol, pooled over scenes) and the median latency per snippet (reading its frames
included, after one warm-up pass over the scenes), with the model card's post-processing and,
unless --mirror / --no-mirror say otherwise, its mirror runs.
Writes results/tradeoff.{md,csv,json,png}.

    python benchmarks/tradeoff.py [--model models/parq-demo] [--scenes 40]
    python benchmarks/tradeoff.py --latency-from benchmarks/results/tradeoff-mean.json

``--latency-from`` re-measures accuracy only and reports the latency column of an earlier
run of the same graphs (its machine named in the table): for a post-processing change on a
machine too busy or too different to time on.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import pathlib
import statistics
import sys

import common

HELD_OUT_SEED = 3000
# parq-synth seeds the demo saw: its training scenes (parq_train.cli.TRAIN_SEED) and the
# validation scenes its card was tuned on (data/val, data/val2); --seed refuses them
DEMO_SEEDS = (1000, 2000, 2001)
ITERATIONS = (1, 2, 4, 8)
QUERIES = (16, 32, 64, 128)


def add_scene_arguments(p: argparse.ArgumentParser, use: str, model: bool = True) -> None:
    """--model (unless ``model`` is false), --scenes, --frames, --size: the demo model and the
    held-out scenes a script ``use``s (this one, error_analysis.py and spread.py read them with
    :func:`scenes_from_arguments`)."""
    if model:
        p.add_argument("--model", default=str(common.ROOT / "models" / "parq-demo"),
                       help=f"model folder to {use} (default models/parq-demo)")
    p.add_argument("--scenes", type=int, default=40,
                   help=f"held-out scenes (of parq-synth --seed) to {use} "
                        "(default 40)")
    p.add_argument("--frames", type=int, default=60,
                   help="frames per held-out scene (default 60)")
    p.add_argument("--size", default="160x120", help="rendered frame size (default 160x120)")
    p.add_argument("--seed", type=int, nargs="+", default=[HELD_OUT_SEED],
                   help=f"parq-synth seed(s) of the held-out scenes, --scenes of each (default "
                        f"{HELD_OUT_SEED}, the documented numbers'); another seed gives a fresh "
                        f"held-out set, except {', '.join(map(str, DEMO_SEEDS))}, which the "
                        "demo was trained or tuned on")


def scenes_from_arguments(args) -> tuple:
    """(held-out scene folders, generated where missing, (width, height)) from the
    arguments of :func:`add_scene_arguments`: --scenes of each --seed, seed by seed."""
    for seed in args.seed:
        if seed in DEMO_SEEDS or seed < 0:
            raise SystemExit(f"--seed {seed}: not a held-out seed (the demo was trained or "
                             f"tuned on {', '.join(map(str, DEMO_SEEDS))}; seeds are >= 0)")
    if len(set(args.seed)) < len(args.seed):
        raise SystemExit("--seed: a seed is given twice")
    size = tuple(int(v) for v in args.size.split("x"))
    return [folder for seed in args.seed
            for folder in held_out_scenes(args.scenes, args.frames, size, seed)], size


def held_out_text(args) -> str:
    """'N held-out scenes (parq-synth seed S, WxH)' for the arguments of
    :func:`add_scene_arguments`, naming every seed."""
    if len(args.seed) == 1:
        return f"{args.scenes} held-out scenes (parq-synth seed {args.seed[0]}, {args.size})"
    return (f"{args.scenes * len(args.seed)} held-out scenes (parq-synth seeds "
            f"{', '.join(map(str, args.seed))}, {args.scenes} each, {args.size})")


def held_out_scenes(scenes: int, frames: int, size, seed: int = HELD_OUT_SEED) -> list:
    """Scene folders 0 .. scenes - 1 of parq-synth ``seed`` at ``size`` (width, height),
    generated where missing into the cache folder of that size and seed
    (held_out_<W>x<H>, with _seed<S> for seeds other than HELD_OUT_SEED)."""
    from parq_synth import generate
    from parq_synth.writer import scene_name

    folder = common.CACHE / (f"held_out_{size[0]}x{size[1]}"
                             + ("" if seed == HELD_OUT_SEED else f"_seed{seed}"))
    generate(folder, scenes, seed, frames=frames, size=size, skip_existing=True,
             jobs=os.cpu_count() or 1)  # the same scenes whatever the processes
    return [folder / scene_name(k) for k in range(scenes)]


def run_scenes(detector, scenes, iters, queries, score_threshold=None, gap=None,
               mirror=None, seen_only=False, **settings) -> tuple:
    """parq-run's pipeline on each scene: ([(fused boxes, ground-truth boxes, up), ...] in
    scene order, per-snippet seconds, a snippet's mirror run included); ``gap``: keyframes
    between a snippet's views, ``mirror``: whether to add mirror runs (None: the model
    card's); ``seen_only``: only the ground-truth boxes some frame shows (parq-eval
    --seen-only); further ``settings``: other scene.RunSettings fields (ray_ratio,
    min_support)."""
    from parq_runtime import evaluation, readers, scene

    pairs, seconds = [], []
    settings = scene.RunSettings(iters=iters, queries=queries, score_threshold=score_threshold,
                                 gap=gap, mirror=mirror, **settings)
    for folder in scenes:
        capture = readers.open_capture(folder)
        result = scene.run(detector, capture, settings)
        truth, up = evaluation.load_ground_truth(folder / "boxes.json", seen_only)
        pairs.append((result.fusion.boxes, truth, up))
        seconds += [s.seconds for s in result.snippets]
    return pairs, seconds


def evaluate_setting(detector, scenes, iters, queries, score_threshold=None,
                     gap=None, mirror=None) -> tuple:
    """(metrics, per-snippet seconds) over the scenes, pooled as parq-eval does; arguments as
    :func:`run_scenes`'s."""
    from parq_runtime import evaluation

    pairs, seconds = run_scenes(detector, scenes, iters, queries, score_threshold, gap, mirror)
    return evaluation.evaluate(pairs, detector.classes), seconds


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_arguments(p, "measure")
    p.add_argument("--threads", type=int, default=None,
                   help="onnxruntime threads (default: its own choice)")
    p.add_argument("--out", default=str(common.RESULTS / "tradeoff"),
                   help="output stem: .md, .csv, .json, .png (default results/tradeoff)")
    p.add_argument("--mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="add each snippet's mirror-image run (default: the model card's run "
                        "setting)")
    p.add_argument("--latency-from", type=pathlib.Path, default=None,
                   help="an earlier run's .json: report its latencies (same graphs) instead "
                        "of timing here")
    args = p.parse_args()
    earlier = json.loads(args.latency_from.read_text()) if args.latency_from else None

    from parq_runtime import Detector

    det = Detector(args.model, threads=args.threads)
    learned = len(det.card.reference_points)
    args.mirror = det.card.run_mirror if args.mirror is None else args.mirror
    scenes, _ = scenes_from_arguments(args)
    # Warm-up pass, not reported: the first setting would otherwise pay for reading the
    # scenes from a cold disk cache (18 ms per snippet instead of 13 at 1 x 16).
    evaluate_setting(det, scenes, 1, min(QUERIES), mirror=args.mirror)
    rows = []
    for iters in ITERATIONS:
        for queries in sorted(set(QUERIES + (learned,))):
            metrics, seconds = evaluate_setting(det, scenes, iters, queries,
                                                mirror=args.mirror)
            row = {"iterations": iters, "queries": queries,
                   "seconds_per_snippet": round(statistics.median(seconds), 5)}
            for t in ("0.25", "0.5", "0.7"):
                row[f"f1@{t}"] = round(metrics[t]["f1"], 4)
                row[f"precision@{t}"] = round(metrics[t]["precision"], 4)
                row[f"recall@{t}"] = round(metrics[t]["recall"], 4)
            if earlier is not None:
                row["seconds_per_snippet"] = next(
                    r["seconds_per_snippet"] for r in earlier["rows"]
                    if (r["iterations"], r["queries"]) == (iters, queries))
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    write(pathlib.Path(args.out), rows, args, learned, earlier)


def write(out, rows, args, learned, earlier=None):
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    machine = common.machine()
    timed = earlier["machine"] if earlier else machine
    record = {"machine": machine, "scenes": args.scenes, "seed": args.seed,
              "mirror": args.mirror, "rows": rows}
    if earlier:
        record["latency_from"] = {"file": str(args.latency_from), "machine": timed}
    out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    source = f" (from {args.latency_from.name}, not timed in this run)" if earlier else ""
    lines = [f"{held_out_text(args)}, 3-view "
             f"snippets{', each also run mirrored' if args.mirror else ''}, "
             f"scene-level F1 (parq-eval); latency = median seconds per "
             f"snippet{' (both runs)' if args.mirror else ''} on {timed['cpu']}, "
             f"{timed['cores']} cores{source}.", "",
             "| iterations | queries | F1@0.25 | F1@0.5 | F1@0.7 | ms / snippet |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        q = f"{r['queries']}" + (" (learned)" if r["queries"] == learned else "")
        lines.append(f"| {r['iterations']} | {q} | {r['f1@0.25']:.3f} | {r['f1@0.5']:.3f} | "
                     f"{r['f1@0.7']:.3f} | {1000 * r['seconds_per_snippet']:.1f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for queries in sorted({r["queries"] for r in rows}):
        sel = [r for r in rows if r["queries"] == queries]
        axes[0].plot([r["iterations"] for r in sel], [r["f1@0.5"] for r in sel], "o-",
                     label=f"{queries} queries")
        axes[1].plot([1000 * r["seconds_per_snippet"] for r in sel], [r["f1@0.5"] for r in sel],
                     "o-", label=f"{queries} queries")
    axes[0].set_xlabel("iterations")
    axes[1].set_xlabel("ms per snippet (median)")
    for ax in axes:
        ax.set_ylabel("F1 at IoU 0.5")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Demo model on held-out generated scenes: accuracy vs compute")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
