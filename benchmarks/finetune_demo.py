"""More training for the demo: its weights, read back out of its graphs, trained on for more
steps, scored on the validation scenes against the demo (the held-out scenes are not spent).

The demo's training checkpoint is not in the repository, so ``parq_export.rebuild`` rebuilds
it from ``models/parq-demo`` (the same function as the graphs, checked).  Its batch norms stay
frozen (a training checkpoint would have them frozen too: parq-train ends by freezing them),
and training continues with the recipe's objective, batch, iterations and schedule shape
(linear warm-up over a tenth of the steps, cosine to 2% of --lr), on parq-train's training
scenes ``--first`` .. ``--first + --scenes - 1`` (parq-synth seed 1000, 30 frames, generated
into --data when missing: the recipe's are 0-1599, so --first 1600 gives new rooms).

The result is exported, with the demo's card settings (post-processing, run setting, query
order: the rebuilt configuration carries them), and scored as parq-run runs it on the
validation scenes, paired against the demo over 10,000 resamples of the scenes (spread.py).
Writes results/finetune_demo-NAME.{md,json}.

    python benchmarks/finetune_demo.py --steps 2000 --lr 1e-4 --name A --val data/val data/val2
    python benchmarks/finetune_demo.py --steps 3000 --lr 1e-4 --first 1600 --name C \\
        --val data/val data/val2
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

import common
import spread
import tradeoff
from parq_train import validation_runs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.validation_arguments(p)
    p.add_argument("--data", type=pathlib.Path, default=common.ROOT / "data" / "train1600",
                   help="parq-train's training scenes (generated where missing)")
    p.add_argument("--first", type=int, default=0, help="first training scene to train on")
    p.add_argument("--scenes", type=int, default=1600, help="training scenes to train on")
    p.add_argument("--steps", type=int, default=2000, help="training steps")
    p.add_argument("--lr", type=float, default=1e-4, help="peak learning rate")
    p.add_argument("--seed", type=int, default=7, help="seed of the batches' order")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all)")
    p.add_argument("--name", default="run", help="names the outputs")
    p.add_argument("--work", type=pathlib.Path, default=common.ROOT / "work" / "finetune",
                   help="folder for the checkpoint and model folders")
    args = p.parse_args()

    import torch

    from parq_export import checkpoint, export, rebuild
    from parq_runtime import Detector, model_card
    from parq_runtime.errors import ParqError
    from parq_train import cli, data, train
    from parq_train.symmetry import folds_of_class

    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        demo = model_card.load(args.model)
        folders = validation_runs.validation_folders(args.val, None)
        model = rebuild.rebuild(args.model)
    except ParqError as e:
        sys.exit(f"finetune_demo: {e}")
    config = model.config
    start = time.perf_counter()
    scenes = data.training_scenes(args.data, args.first + args.scenes, cli.TRAIN_SEED, 30,
                                  config.image_size, jobs=2)[args.first:]
    snippets = data.load_scenes(scenes, config)
    model, history = train.train(config, snippets, args.steps, args.seed,
                                 folds_of_class(config.classes), batch_size=4, lr=args.lr,
                                 iterations=config.iterations, log_every=250, model=model)
    minutes = (time.perf_counter() - start) / 60
    args.work.mkdir(parents=True, exist_ok=True)
    ckpt = args.work / f"{args.name}.pt"
    checkpoint.save(ckpt, model, {"finetune": {k: str(v) for k, v in vars(args).items()},
                                  "history": history})
    # the rebuilt configuration carries the demo card's post-processing, run setting and
    # query order (rebuild.card_config), so the export has the demo's card
    tuned = args.work / f"{args.name}-model"
    export.export(ckpt, tuned, overwrite=True, log=lambda *_: None)
    iters, queries = demo.run_setting()
    counts = []
    for folder in (args.model, tuned):
        detector = Detector(folder)
        pairs, _ = tradeoff.run_scenes(detector, folders, iters, queries)
        counts.append(spread.counts_of(pairs, detector.classes))
    stats = spread.spread(counts, 10000, 40)
    machine = common.machine()
    first, last = history[0], history[-1]
    lines = [f"{args.model.name} trained on: {args.steps} steps, peak learning rate {args.lr}, "
             f"training scenes {args.first}-{args.first + args.scenes - 1} ({len(snippets)} "
             f"snippets), seed {args.seed}; {minutes:.1f} min with the scenes' loading "
             f"({machine['cpu']}, torch threads: {torch.get_num_threads()}). Training loss "
             f"{first['total']:.3f} over the first 250 steps, {last['total']:.3f} over the "
             "last 250.", "",
             f"Scored on {len(folders)} validation scenes ({', '.join(map(str, args.val))}) "
             f"with the demo's card (post-processing, {iters} x {queries}, mirror runs), paired "
             "against the demo:", "",
             "| model | F1@0.25 (90%) | vs demo | F1@0.5 (90%) | vs demo |",
             "|---|---|---|---|---|",
             f"| {args.model.name} | " + " | ".join(spread.paired_cells(stats[0])) + " |",
             f"| trained on ({args.name}) | " + " | ".join(spread.paired_cells(stats[1])) + " |"]
    common.write_report(common.HERE / "results" / f"finetune_demo-{args.name}", lines,
                        {"args": {k: str(v) for k, v in vars(args).items()},
                         "history": history, "stats": stats, "minutes": minutes,
                         "f1": np.round([spread.f1(c.sum(axis=0)) for c in counts], 4).tolist()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
