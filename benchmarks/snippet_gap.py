"""Does a wider baseline between a snippet's views help? Two short trainings of the demo
configuration from one pretrained backbone, the same seed and scenes, differing only in the gap
between a training snippet's views (parq-train --gap); each is then tuned, exported and scored.

    python benchmarks/snippet_gap.py pretrain work/exp/pre.pt --steps 3000
    python benchmarks/snippet_gap.py train work/exp/pre.pt work/exp/gap1.pt --gap 1 --threads 1
    python benchmarks/snippet_gap.py train work/exp/pre.pt work/exp/gap3.pt --gap 3 --threads 1
    python benchmarks/snippet_gap.py score work/exp/gap3.pt work/exp/gap3

``train`` reads parq-train's 1,600 scenes (data/train1600, generated when missing); ``score``
tunes the post-processing on data/val (python -m parq_train.tune), exports to the folder, prints
held-out F1 (tradeoff.py's 40 scenes) at 1, 2 and 4 iterations x 32 queries, at 2 x 32 with
the other gap (1 <-> 3), and writes error_analysis.py's tables (ray split included) beside the
folder.  docs/demo-experiments.md, "Wider snippets", gives what the runs of 2026-12-01 printed.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import common

TRAIN = pathlib.Path("data/train1600")


def pretrain(args) -> None:
    import torch

    from parq_train import data, pretrain as backbone_pretraining, train
    from parq_train.cli import TRAIN_SEED, demo_config

    torch.set_num_threads(args.threads)
    config = demo_config()
    folders = data.training_scenes(TRAIN, 1600, TRAIN_SEED, 30, config.image_size, jobs=2)
    model = train.new_model(config, args.seed, None)
    backbone_pretraining.pretrain(model.backbone, config, folders, args.steps, args.seed,
                                  log_every=250)
    backbone_pretraining.save_backbone(
        args.output, model.backbone,
        backbone_pretraining.record_of(config, args.steps, args.seed, TRAIN_SEED, folders, 30,
                                       command="benchmarks/snippet_gap.py"))


def train_gap(args) -> None:
    import torch

    from parq_export import checkpoint
    from parq_train import data, pretrain, train
    from parq_train.cli import TRAIN_SEED, demo_config
    from parq_train.symmetry import folds_of_class

    torch.set_num_threads(args.threads)
    config = demo_config(snippet_gap=args.gap)
    folders = data.training_scenes(TRAIN, 1600, TRAIN_SEED, 30, config.image_size, jobs=2)
    snippets = data.load_scenes(folders, config)
    model = train.new_model(config, args.seed, snippets)
    pretrain.set_backbone(model.backbone, pretrain.read_backbone(args.pretrained, config)[0],
                          args.pretrained)
    model, history = train.train(config, snippets, args.steps, args.seed,
                                 folds_of_class(config.classes), batch_size=4, iterations=4,
                                 lr=5e-4, log_every=250, model=model, form="cached")
    record = {"experiment": "benchmarks/snippet_gap.py", "gap": args.gap, "steps": args.steps,
              "seed": args.seed, "final_loss": history[-1]}
    model.config = model.config.replace(extra={"training": record})
    checkpoint.save(args.output, model, {"training": record, "history": history})


def score(args) -> None:
    import error_analysis
    import tradeoff

    from parq_export import cli as export_cli
    from parq_runtime import Detector
    from parq_train import tune

    tuned = args.folder.with_name(args.folder.name + "-tuned.pt")
    if tune.main([str(args.checkpoint), "--data", "data/val", "-o", str(tuned)]) or \
            export_cli.main([str(tuned), "-o", str(args.folder), "--force", "--no-check"]):
        sys.exit("snippet_gap: tuning or export failed")
    detector = Detector(args.folder)
    gap = detector.card.snippet_gap
    scenes = tradeoff.held_out_scenes(40, 60, (160, 120))
    for iters in (1, 2, 4):
        m, _ = tradeoff.evaluate_setting(detector, scenes, iters, 32)
        print(f"{args.folder} (gap {gap}), {iters} x 32: " + f1_line(m), flush=True)
    other = 3 if gap == 1 else 1
    m, _ = tradeoff.evaluate_setting(detector, scenes, 2, 32, gap=other)
    print(f"{args.folder} run at gap {other}, 2 x 32: " + f1_line(m), flush=True)
    sys.argv = ["error_analysis", "--model", str(args.folder), "--settings", "2x32",
                "--out", str(args.folder.with_name(args.folder.name + "-errors"))]
    error_analysis.main()


def f1_line(metrics: dict) -> str:
    return "  ".join(f"F1@{t} {metrics[t]['f1']:.3f}" for t in ("0.25", "0.5", "0.7"))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("pretrain", help="pretrain the demo backbone once")
    a.add_argument("output", type=pathlib.Path, help="backbone weights to write (.pt)")
    a.add_argument("--steps", type=int, default=3000, help="pretraining steps (default 3000)")
    b = sub.add_parser("train", help="train from the pretrained backbone with one gap")
    b.add_argument("pretrained", type=pathlib.Path, help="backbone weights from 'pretrain'")
    b.add_argument("output", type=pathlib.Path, help="checkpoint to write (.pt)")
    b.add_argument("--gap", type=int, required=True,
                   help="keyframes between a training snippet's views")
    b.add_argument("--steps", type=int, default=4500, help="training steps (default 4500)")
    c = sub.add_parser("score", help="tune, export and score a checkpoint from 'train'")
    c.add_argument("checkpoint", type=pathlib.Path, help="checkpoint from 'train'")
    c.add_argument("folder", type=pathlib.Path, help="model folder to export to")
    for q in (a, b):
        q.add_argument("--seed", type=int, default=0, help="seed (default 0)")
        q.add_argument("--threads", type=int, default=2,
                       help="torch threads (default 2; the runs below used 1 each, side by "
                            "side)")
    args = p.parse_args()
    {"pretrain": pretrain, "train": train_gap, "score": score}[args.command](args)


if __name__ == "__main__":
    main()
