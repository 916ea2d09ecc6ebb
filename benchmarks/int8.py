"""Does the int8 image encoder pay?  Speed on the authors' configuration, F1 on the demo.

1. Speed: the authors' configuration (ResNet50, 1024 channels, 3 views of 320x240, seeded
   weights) exported twice, fp32 and ``parq-export --quantize int8`` (calibrated on generated
   scenes at 320x240); backbone.onnx timed interleaved, median over --runs after a warm-up.
2. Accuracy: the demo model's checkpoint exported both ways; scene-level F1 on the held-out
   scenes of benchmarks/tradeoff.py (parq-synth seed 3000) at parq-run's defaults.  Without
   --demo-checkpoint (the shipped demo's is not in git: rebuild.sh makes it), speed only.

The bar (issue 4): ship int8 only if it is faster and costs at most 1 F1 point.
Writes results/int8.{md,json}.

    python benchmarks/int8.py [--demo-checkpoint work/demo-tuned.pt] [--scenes 40] [--runs 7]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import sys
import time

import numpy as np

import common
import tradeoff


def export_pair(checkpoint, name: str, calibration) -> tuple:
    digest = hashlib.sha256(pathlib.Path(checkpoint).read_bytes()).hexdigest()
    paths = []
    for quantize in (None, "int8"):
        out = common.CACHE / f"{name}_{quantize or 'fp32'}"
        # re-export also when the checkpoint changed (a re-tuned demo has new post-processing)
        if common.stale(out, digest):
            common.export_cached(checkpoint, out, quantize=quantize, calibration=calibration)
        paths.append(out)
    return tuple(paths)


def backbone_times(model_dirs, runs: int) -> list:
    from parq_runtime import Detector

    images, K, T = common.golden_snippet()
    detectors = [Detector(d) for d in model_dirs]
    prepared = detectors[0].prepare(images, K, T)
    times = [[] for _ in detectors]
    for run in range(runs + 1):
        for i in (range(len(detectors)) if run % 2 == 0 else reversed(range(len(detectors)))):
            t = time.perf_counter()
            detectors[i].encode(prepared[0], prepared[1], prepared[3], cached=False)
            if run > 0:
                times[i].append(time.perf_counter() - t)
    return [common.stats(t) for t in times]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--demo-checkpoint", type=pathlib.Path, default=None,
                   help="tuned demo checkpoint (parq_train.tune) to export in fp32 and int8 "
                        "for the F1 change (default: none, speed only)")
    p.add_argument("--scenes", type=int, default=40,
                   help="held-out scenes scored for the F1 change (default 40)")
    p.add_argument("--runs", type=int, default=7,
                   help="timed runs after warm-up (default 7)")
    p.add_argument("--out", default=str(common.RESULTS / "int8"),
                   help="output stem: .md, .json (default results/int8)")
    args = p.parse_args()

    from parq_runtime import Detector
    from parq_export.quantize import generate_calibration

    calibration = generate_calibration(common.CACHE / "calibration_320x240", (320, 240))
    official = export_pair(common.official_checkpoint(), "official", calibration)
    speed = backbone_times(official, args.runs)
    print(f"backbone fp32 {speed[0]['median']:.3f} s, int8 {speed[1]['median']:.3f} s",
          file=sys.stderr)

    f1 = []
    if args.demo_checkpoint is not None:
        demo = export_pair(args.demo_checkpoint, "demo", None)
        scenes = tradeoff.held_out_scenes(args.scenes, 60, (160, 120))
        for model_dir in demo:
            metrics, _ = tradeoff.evaluate_setting(Detector(model_dir), scenes, 2, 32)
            f1.append({t: metrics[t]["f1"] for t in metrics})
    card = json.loads((official[1] / "model.json").read_text())["quantization"]
    faster = speed[1]["median"] < speed[0]["median"]
    machine = common.machine()
    lines = [f"Machine: {machine['cpu']}, {machine['cores']} cores ({', '.join(machine['isa'])});"
             f" onnxruntime {machine['onnxruntime']}.", "",
             "| | fp32 | int8 |", "|---|---:|---:|",
             f"| backbone, authors' configuration (s, median of {args.runs}) | "
             f"{speed[0]['median']:.3f} | {speed[1]['median']:.3f} |",
             f"| memory max abs diff vs torch (relative) | - | "
             f"{card['memory']:.3g} ({card['memory_relative']:.3g}) |"]
    ratio = speed[0]["median"] / speed[1]["median"]
    if f1:
        for t in ("0.25", "0.5", "0.7"):
            lines.append(f"| demo F1@{t}, {args.scenes} held-out scenes | {f1[0][t]:.3f} | "
                         f"{f1[1][t]:.3f} |")
        cost = max(100 * (f1[0][t] - f1[1][t]) for t in f1[0])
        verdict = "ships" if faster and cost <= 1.0 else "does not ship"
        lines += ["", f"int8 is {ratio:.2f}x the fp32 backbone's speed and costs up to "
                  f"{cost:.1f} F1 points: it {verdict} (bar: faster and at most 1 point)."]
    else:
        verdict = "is faster" if faster else "is not faster: it does not ship"
        lines += ["", f"int8 is {ratio:.2f}x the fp32 backbone's speed; F1 not measured (no "
                  f"--demo-checkpoint): it {verdict}."]
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(
        {"machine": machine, "speed": speed, "f1": f1, "quantization": card,
         "verdict": verdict}, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
