"""How far bfloat16 autocast moves a float32 model's box centres, forward pass only.

    python benchmarks/bf16_forward.py work/g3/g3.pt --val data/val

Runs the checkpoint on generalization.py's snippets of the first 10 validation scenes (every
4th), in batches of 8, 4 iterations, evaluation form, training's attention form ("cached"),
once in float32 and once under the CPU autocast that ``parq-train --bf16`` trains with, and
prints the median and 90th percentile of the distance between the two runs' centres, per
iteration, over every query.  It separates the rounding of bfloat16 arithmetic from what a
model trained under it learned (benchmarks/results/bf16_batch4.md).
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np
import torch

import generalization
from parq_export import checkpoint
from parq_train.train import to_batch

ITERATIONS = generalization.ITERATIONS


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=pathlib.Path, help="a float32-trained checkpoint (.pt)")
    p.add_argument("--val", type=pathlib.Path, default=pathlib.Path("data/val"),
                   help="folder of validation scenes (default data/val)")
    args = p.parse_args()
    model = checkpoint.load(args.checkpoint).model()
    items = generalization.snippets(args.val, 10, model.config)
    distances = [[] for _ in range(ITERATIONS)]
    with torch.no_grad():
        for i in range(0, len(items), 8):
            images, camera, T_local_camera, _ = to_batch(items[i:i + 8])
            exact = model(images, camera, T_local_camera, iterations=ITERATIONS, form="cached")
            with torch.autocast("cpu", dtype=torch.bfloat16):
                rounded = model(images, camera, T_local_camera, iterations=ITERATIONS,
                                form="cached")
            for it in range(ITERATIONS):
                d = (exact[it]["center"].float() - rounded[it]["center"].float()).norm(dim=-1)
                distances[it].append(d.flatten().numpy())
    for it, parts in enumerate(distances):
        d = np.concatenate(parts)
        print(f"iteration {it + 1}: centre moved by bfloat16 autocast, median {np.median(d):.4f} m,"
              f" 90th percentile {np.percentile(d, 90):.4f} m ({d.size} queries,"
              f" {len(items)} snippets)")


if __name__ == "__main__":
    main()
