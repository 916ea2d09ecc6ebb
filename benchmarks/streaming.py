"""Per-keyframe cost of a video with sliding windows: streaming versus recomputing.

Over a walk of --frames keyframes, snippets are 3-view windows moved one keyframe at a time
(stride 1), so every keyframe starts a new snippet.  Streaming (parq_runtime.FeatureCache, what
parq-run does when the stride is under the window) runs the per-image part of the backbone
(ResNet-FPN) once per frame and reuses it in every snippet that holds the frame; only the
pose-dependent part (ray encoding, memory, attention operands) and the loop run per snippet.
Recomputing runs the whole backbone on all three views of every snippet.

The authors' configuration (ResNet50, 1024 channels, 320x240; seeded weights), frames of the
golden case at ScanNet's colour size, 32 queries x 2 iterations by default.  Medians over
every snippet after the first of each pass, --passes passes after a warm-up pass, interleaved.
Writes results/streaming.{md,json}.

    python benchmarks/streaming.py [--frames 12] [--passes 3] [--queries 32] [--iters 2]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

import common


def walk(frames: int, images, K) -> list:
    """(image, K, T_world_camera) per keyframe: 15 cm and 5 degrees apart, 1.5 m high."""
    from parq_runtime.geometry import camera_pose

    return [(images[i % len(images)], K,
             camera_pose([0.15 * i, 0.0, 1.5], np.radians(5.0 * i), np.radians(20.0)))
            for i in range(frames)]


def one_pass(det, keyframes, queries, iters, streaming: bool) -> list:
    """Stage timings of each snippet after the first."""
    from parq_runtime.detector import FeatureCache

    cache = FeatureCache(3) if streaming else None
    out = []
    for start in range(len(keyframes) - 2):
        window = list(range(start, start + 3))
        result = det.detect([keyframes[i][0] for i in window], keyframes[0][1],
                            np.stack([keyframes[i][2] for i in window]), iters=iters,
                            queries=queries, frame_keys=window if streaming else None,
                            cache=cache)
        t = result.timings
        if start > 0:
            out.append({"preprocess": t["preprocess"], "backbone": t["backbone"],
                        "loop": sum(t["iterations"]), "postprocess": t["postprocess"],
                        "total": t["preprocess"] + t["backbone"] + sum(t["iterations"])
                        + t["postprocess"]})
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=12,
                   help="keyframes in the streamed video (default 12)")
    p.add_argument("--passes", type=int, default=3,
                   help="timed passes over the video (default 3)")
    p.add_argument("--queries", type=int, default=32,
                   help="queries (default 32)")
    p.add_argument("--iters", type=int, default=2,
                   help="recurrent iterations (default 2)")
    p.add_argument("--out", default=str(common.RESULTS / "streaming"),
                   help="output stem: .md, .json (default results/streaming)")
    args = p.parse_args()

    from parq_runtime import Detector

    det = Detector(common.official_model())
    images, K, _ = common.golden_snippet()
    keyframes = walk(args.frames, images, np.asarray(K).reshape(-1, 3, 3)[0])
    samples = {"streaming": [], "recompute": []}
    for n in range(args.passes + 1):
        order = ("streaming", "recompute") if n % 2 == 0 else ("recompute", "streaming")
        for mode in order:
            timings = one_pass(det, keyframes, args.queries, args.iters, mode == "streaming")
            if n > 0:
                samples[mode] += timings
        print(f"pass {n + 1}/{args.passes + 1}", file=sys.stderr, flush=True)
    summary = {mode: {stage: common.stats([t[stage] for t in runs])
                      for stage in runs[0]} for mode, runs in samples.items()}
    machine = common.machine()
    lines = [f"Machine: {machine['cpu']}, {machine['cores']} cores. 3-view windows, stride 1, "
             f"{args.queries} queries x {args.iters} iterations; seconds per keyframe "
             f"(= per snippet), median [quartiles] of {len(samples['streaming'])} snippets.",
             "", "| stage | recompute every view | streaming | saved |", "|---|---:|---:|---:|"]
    for stage in ("preprocess", "backbone", "loop", "postprocess", "total"):
        a, b = summary["recompute"][stage], summary["streaming"][stage]
        lines.append(f"| {stage} | {a['median']:.4f} [{a['p25']:.4f}, {a['p75']:.4f}] | "
                     f"{b['median']:.4f} [{b['p25']:.4f}, {b['p75']:.4f}] | "
                     f"{100 * (1 - b['median'] / a['median']):.0f}% |")
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(
        {"machine": machine, "args": vars(args), "summary": summary}, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
