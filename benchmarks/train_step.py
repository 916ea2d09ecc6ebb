"""Seconds per training step of the demo configuration: float32 against bfloat16 autocast
(parq-train --bf16), at batch 4 (the demo's) and 8, on this machine's cores.

Each measurement is parq_train.train.train itself, timed step by step through its log
callback, on snippets of the first --scenes training scenes.  The configurations are
interleaved round after round so that drift of a noisy machine hits them alike; the first
--warmup steps of every call are dropped.  Writes results/train_step.{md,json}.

    python benchmarks/train_step.py [--data data/train1600] [--rounds 3] [--steps 14]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import common

CONFIGURATIONS = (("float32", 4), ("bfloat16", 4), ("float32", 8), ("bfloat16", 8))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=pathlib.Path, default=pathlib.Path("data/train1600"),
                   help="parq-train's training scenes (default data/train1600)")
    p.add_argument("--scenes", type=int, default=30, help="scenes loaded (default 30)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    p.add_argument("--steps", type=int, default=14, help="steps per call (default 14)")
    p.add_argument("--warmup", type=int, default=4,
                   help="first steps of each call not counted (default 4)")
    p.add_argument("--out", default=str(common.RESULTS / "train_step"),
                   help="output path without extension (default results/train_step)")
    args = p.parse_args()
    folders = sorted(f.parent for f in args.data.glob("*/boxes.json"))[:args.scenes]
    if not folders:
        sys.exit(f"train_step: {args.data}: no generated scenes (run parq-train or parq-synth)")

    import torch

    from parq_train import data, train
    from parq_train.cli import demo_config
    from parq_train.symmetry import folds_of_class

    config = demo_config()
    snippets = data.load_scenes(folders, config, log=lambda *_: None)
    folds = folds_of_class(config.classes)
    times = {c: [] for c in CONFIGURATIONS}
    for _ in range(args.rounds):
        for precision, batch in CONFIGURATIONS:
            stamps = []
            start = time.perf_counter()
            train.train(config, snippets, args.steps, seed=0, folds_of_class=folds,
                        batch_size=batch, log=lambda *_: stamps.append(time.perf_counter()),
                        log_every=1, bf16=precision == "bfloat16")
            ends = [start] + stamps
            times[(precision, batch)] += [b - a for a, b in zip(ends, ends[1:])][args.warmup:]
    rows = []
    for (precision, batch), values in times.items():
        s = common.stats(values)
        rows.append({"precision": precision, "batch": batch, **s,
                     "snippets_per_s": batch / s["median"]})
    base = {r["batch"]: r["snippets_per_s"] for r in rows if r["precision"] == "float32"}
    m = common.machine()
    lines = [f"Machine: {m['cpu']}, {m['cores']} cores ({', '.join(m['isa'])}), torch "
             f"{m['torch']}, {torch.get_num_threads()} threads. The demo configuration "
             f"(160x120, 3 views, 4 iterations), {len(snippets)} snippets of {len(folders)} "
             f"training scenes; seconds per step, medians [quartiles] of {rows[0]['n']} steps "
             f"({args.rounds} interleaved rounds).", "",
             "| precision | batch | s / step | snippets / s | vs float32, same batch | "
             "vs the demo's float32 batch 4 |", "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['precision']} | {r['batch']} | {r['median']:.3f} "
                     f"[{r['p25']:.3f}, {r['p75']:.3f}] | {r['snippets_per_s']:.1f} | "
                     f"{r['snippets_per_s'] / base[r['batch']]:.2f}x | "
                     f"{r['snippets_per_s'] / base[4]:.2f}x |")
    out = pathlib.Path(args.out)
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"machine": m, "rows": rows}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
