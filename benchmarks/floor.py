"""How well and how fast parq-run finds the floor (parq_runtime.floor) on held-out scenes.

Runs the model's whole pipeline on each held-out scene (parq-synth seed 3000, tradeoff.py's
cache) at its card's run setting, as parq-run does, and compares the floor it used with the
truth: parq-synth's floor is z = 0, which is also the lowest ground-truth box bottom.  The
sweep is timed again on its own, after the run (median of --repeats timings a scene, the
frames read from disk each time as parq-run reads them), since the pipeline's time is mostly
the network's.  Prints and writes results/floor.{md,json} (--out):

* how many scenes got a floor, and the error of those floors (median, 90th percentile, most),
  overall and by floor kind (tiles, planks, carpet: scene.json's room style);
* the median seconds the sweep takes a capture.

    python benchmarks/floor.py --scenes 120
    python benchmarks/floor.py --scenes 40 --size 320x240 --out results/floor-320
"""
from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import time

import numpy as np

import common
import tradeoff


def measure(detector, scenes: list, repeats: int) -> list:
    """Per scene: {"scene", "kind", "floor" (m, None: none), "truth", "seconds"}."""
    from parq_runtime import evaluation, floor, readers, scene

    rows = []
    for folder in scenes:
        capture = readers.open_capture(folder)
        result = scene.run(detector, capture, scene.RunSettings())
        truth, up = evaluation.load_ground_truth(folder / "boxes.json")
        up = np.asarray(up, dtype=np.float64)
        lowest = min(float(b.center @ up) - b.size[1] / 2 for b in truth)
        guess = result.fusion.floor_guess()
        seconds = []
        for _ in range(repeats if guess is not None else 0):
            start = time.perf_counter()
            floor.candidates(readers.open_capture(folder).frames, capture.up, near=guess)
            seconds.append(time.perf_counter() - start)
        room = json.loads((folder / "scene.json").read_text())["room"]["style"]["floor"]
        rows.append({"scene": folder.name, "kind": room["kind"],
                     "floor": None if result.floor is None else result.floor["height"],
                     "truth": lowest,
                     "seconds": statistics.median(seconds) if seconds else None})
    return rows


def summary(rows: list) -> dict:
    def of(subset):
        errors = [abs(r["floor"] - r["truth"]) for r in subset if r["floor"] is not None]
        out = {"scenes": len(subset), "found": len(errors)}
        if errors:
            out.update(median_error_m=round(float(np.median(errors)), 4),
                       p90_error_m=round(float(np.quantile(errors, 0.9)), 4),
                       max_error_m=round(max(errors), 4),
                       over_3cm=int(sum(e > 0.03 for e in errors)))
        return out

    kinds = sorted({r["kind"] for r in rows})
    timed = [r["seconds"] for r in rows if r["seconds"] is not None]
    return {"all": of(rows), **{k: of([r for r in rows if r["kind"] == k]) for k in kinds},
            "median_sweep_seconds": round(statistics.median(timed), 3) if timed else None}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tradeoff.add_scene_arguments(p, "run")
    p.add_argument("--repeats", type=int, default=3,
                   help="timings of the sweep a scene, median kept (default 3)")
    p.add_argument("--out", default=str(common.RESULTS / "floor"),
                   help="output stem: .md and .json (default results/floor)")
    args = p.parse_args()
    from parq_runtime import Detector

    scenes, _ = tradeoff.scenes_from_arguments(args)
    detector = Detector(args.model)
    rows = measure(detector, scenes, args.repeats)
    result = summary(rows)
    machine = common.machine()
    lines = [f"{tradeoff.held_out_text(args)}, {args.model} at its card's run setting; floor "
             f"found by parq-run's pipeline against the truth (z = 0); sweep seconds: median "
             f"of {args.repeats} a scene, median over scenes, on "
             f"{machine.get('cpu', 'this CPU')}.", "",
             "| floors | scenes | found | median error | 90% within | most | over 3 cm |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for key, s in result.items():
        if not isinstance(s, dict):
            continue
        if s["found"]:
            lines.append(f"| {key} | {s['scenes']} | {s['found']} | {s['median_error_m']:.4f} m "
                         f"| {s['p90_error_m']:.4f} m | {s['max_error_m']:.3f} m | "
                         f"{s['over_3cm']} |")
        else:
            lines.append(f"| {key} | {s['scenes']} | 0 | | | | |")
    lines += ["", f"Sweep: {result['median_sweep_seconds']} s a capture (median)."]
    text = "\n".join(lines)
    print(text)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text + "\n")
    out.with_suffix(".json").write_text(json.dumps(
        {"machine": machine, "model": args.model, "scenes": len(scenes), "size": args.size,
         "summary": result, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
