"""onnxruntime session options, each measured: graph optimisation level, intra-op threads and
spinning (``session.intra_op.allow_spinning``) of neither, one or both sessions.

The authors' configuration (ResNet50, 1024 channels, 3 views of 320x240, seeded weights), end
to end through parq_runtime.Detector at 32 queries x 2 iterations and 256 x 8.  Configurations
are interleaved run after run so that drift of this noisy machine hits them alike; medians and
quartiles over --runs after --warmup.  Writes results/session_options.{md,json}.

    python benchmarks/session_options.py [--runs 5]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import common

SETTINGS = ((32, 2), (256, 8))


def configurations(cores: int) -> list:
    """(name, threads, spinning, optimisation level); the runtime's choice first.  spinning:
    which sessions' idle workers spin: none, the layer's or both (backbone and layer)."""
    return [("runtime default: all, no spinning, one thread per core", None, "none", "all"),
            ("optimisation: extended", None, "none", "extended"),
            ("optimisation: basic", None, "none", "basic"),
            ("spinning: layer session", None, "layer", "all"),
            ("spinning: both sessions", None, "both", "all"),
            ("1 thread", 1, "none", "all")] + \
        ([(f"{2 * cores} threads", 2 * cores, "none", "all")] if cores > 1 else [])


def detector(model_dir, threads, spinning, level):
    import onnxruntime as ort

    from parq_runtime import Detector, sessions

    levels = {"basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    saved = sessions.GRAPH_OPTIMIZATION
    sessions.GRAPH_OPTIMIZATION = levels[level]
    try:
        det = Detector(model_dir, threads=threads, spinning=spinning != "none")
        if spinning == "both":  # the Detector never lets the backbone spin; measure why
            det.backbone = sessions.create(det.card.graph_path("backbone"), threads,
                                           spinning=True)
        return det
    finally:
        sessions.GRAPH_OPTIMIZATION = saved


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5,
                   help="timed runs per option set after warm-up (default 5)")
    p.add_argument("--warmup", type=int, default=1,
                   help="untimed warm-up runs (default 1)")
    p.add_argument("--out", default=str(common.RESULTS / "session_options"),
                   help="output stem: .md, .json (default results/session_options)")
    args = p.parse_args()

    images, K, T = common.golden_snippet()
    model_dir = common.official_model()
    configs = configurations(os.cpu_count() or 1)
    detectors = [detector(model_dir, *c[1:]) for c in configs]
    times = {(c[0], s): [] for c in configs for s in SETTINGS}
    first = {(c[0], s): [] for c in configs for s in SETTINGS}  # the iteration after the backbone
    for run in range(args.warmup + args.runs):
        order = range(len(configs)) if run % 2 == 0 else reversed(range(len(configs)))
        for i in order:
            for queries, iters in SETTINGS:
                time.sleep(0.2)  # spinning pools of the previous configuration go idle first
                result = detectors[i].detect(images, K, T, iters=iters, queries=queries)
                if run >= args.warmup:
                    t = result.timings
                    times[(configs[i][0], (queries, iters))].append(
                        t["preprocess"] + t["backbone"] + sum(t["iterations"])
                        + t["postprocess"])
                    first[(configs[i][0], (queries, iters))].append(t["iterations"][0])
        print(f"run {run + 1}/{args.warmup + args.runs}", file=sys.stderr, flush=True)
    rows = [{"configuration": c[0], "threads": c[1], "spinning": c[2], "optimization": c[3],
             "queries": q, "iterations": i, **common.stats(times[(c[0], (q, i))]),
             "first_iteration": common.stats(first[(c[0], (q, i))])}
            for c in configs for q, i in SETTINGS]
    machine = common.machine()
    lines = [f"Machine: {machine['cpu']}, {machine['cores']} cores; onnxruntime "
             f"{machine['onnxruntime']}. End-to-end seconds per snippet, median [quartiles] "
             f"of {args.runs} interleaved runs; in brackets after the total, the first "
             f"iteration's milliseconds (the one that follows the backbone).", "",
             "| configuration | 32 queries, 2 iterations | 256 queries, 8 iterations |",
             "|---|---:|---:|"]
    for c in configs:
        cells = []
        for q, i in SETTINGS:
            r = next(r for r in rows if r["configuration"] == c[0] and r["queries"] == q)
            cells.append(f"{r['median']:.3f} [{r['p25']:.3f}, {r['p75']:.3f}] "
                         f"({r['first_iteration']['median'] * 1e3:.0f} ms)")
        lines.append(f"| {c[0]} | " + " | ".join(cells) + " |")
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"machine": machine, "rows": rows},
                                                   indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
