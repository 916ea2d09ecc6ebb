"""How a trained checkpoint does on scenes it trained on against scenes it never saw: the
training objective's parts and the matched center error, per iteration.

    python benchmarks/generalization.py work/demo.pt --train data/train --val data/val

Each scene folder gives every 4th snippet (3 views, as parq-train cuts them); the model runs in
evaluation form (frozen norms, no colour jitter) with 4 iterations, the training depth.
"center error" is the distance from each target to the prediction the Hungarian algorithm
gives it (cost: center distance minus the class probability), median over targets; "along
ray" and "lateral" split the last iteration's error along the ray from the middle view's
camera and across it.  A large train/validation gap in the loss parts means the model learned
the training scenes, not the task: docs/demo-experiments.md, "More scenes", reads it that way.
"""
from __future__ import annotations

import argparse
import pathlib

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from parq_export import checkpoint
from parq_train import loss, train
from parq_train.data import scene_snippets
from parq_train.symmetry import folds_of_class

ITERATIONS = 4


def snippets(root: pathlib.Path, scenes: int, config) -> list:
    folders = sorted(p for p in root.iterdir() if (p / "boxes.json").is_file())[:scenes]
    return [s for f in folders for s in scene_snippets(f, config)[::4]]


def measure(model, items: list) -> dict:
    config = model.config
    folds = torch.as_tensor(folds_of_class(config.classes))
    parts, errors, along, lateral = {}, [[] for _ in range(ITERATIONS)], [], []
    with torch.no_grad():
        for i in range(0, len(items), 8):
            batch = items[i:i + 8]
            images, camera, T_local_camera, targets = train.to_batch(batch)
            outputs = model(images, camera, T_local_camera, iterations=ITERATIONS,
                            form="cached")
            _, p = loss.total_loss(outputs, targets, folds, len(config.classes))
            for k, v in p.items():
                parts[k] = parts.get(k, 0.0) + v * len(batch)
            for it, out in enumerate(outputs):
                for b, target in enumerate(targets):
                    if len(target["labels"]) == 0:
                        continue
                    centers = target["centers"].double()
                    cost = torch.cdist(out["center"][b].double(), centers) \
                        - out["logits"][b].softmax(-1)[:, target["labels"]].double()
                    rows, cols = linear_sum_assignment(cost.numpy())
                    error = (out["center"][b][rows] - target["centers"][cols]).numpy()
                    errors[it] += list(np.linalg.norm(error, axis=1))
                    if it == ITERATIONS - 1:
                        camera_local = batch[b].T_local_camera[len(batch[b].T_local_camera) // 2]
                        ray = target["centers"][cols].numpy() - camera_local[:3, 3]
                        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
                        a = (error * ray).sum(1)
                        along += list(np.abs(a))
                        lateral += list(np.linalg.norm(error - a[:, None] * ray, axis=1))
    return {"snippets": len(items), **{k: v / len(items) for k, v in parts.items()},
            "center_error": [float(np.median(e)) for e in errors],
            "along_ray": float(np.median(along)), "lateral": float(np.median(lateral))}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=pathlib.Path, help="trained checkpoint (parq-train)")
    p.add_argument("--train", type=pathlib.Path, required=True,
                   help="the scene folder it trained on")
    p.add_argument("--val", type=pathlib.Path, default=pathlib.Path("data/val"),
                   help="scenes it never saw (default data/val)")
    p.add_argument("--scenes", type=int, default=20,
                   help="first scenes of each folder to use (default 20)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = checkpoint.load(args.checkpoint).model()
    print(f"{args.checkpoint}: objective parts (unweighted) and median center error (m)")
    print("| scenes | snippets | center | size | rotation | class | center error by iteration "
          "| along ray | lateral |")
    print("|---|---:|---:|---:|---:|---:|---|---:|---:|")
    for name, root in (("training", args.train), ("validation", args.val)):
        m = measure(model, snippets(root, args.scenes, model.config))
        errors = " / ".join(f"{e:.3f}" for e in m["center_error"])
        print(f"| {name} | {m['snippets']} | {m['center']:.3f} | {m['size']:.3f} | "
              f"{m['rotation']:.3f} | {m['class']:.3f} | {errors} | {m['along_ray']:.3f} | "
              f"{m['lateral']:.3f} |")


if __name__ == "__main__":
    main()
