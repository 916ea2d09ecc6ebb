"""parq-train: generate scenes and train a small PARQ on them, on the CPU.

    parq-train demo.pt --seed 0

generates the training scenes (parq-synth, seeds of the ``train`` range) into --data, the
ones not there already (a folder made with other frame counts or sizes is refused), trains the
demo configuration for --steps steps (or as many as --minutes holds) and writes a checkpoint
in this package's format whose config records how it was made (command, seed, data,
duration); ``parq-export`` copies that record into the model card.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import pathlib
import sys
import time

from parq_runtime.arguments import (OneLineParser, at_most, finite, non_negative_float,
                                    non_negative_int, positive_float, positive_int, score)
from parq_runtime.errors import ParqError

from .budget import MIN_STEPS, PLAN_AT, planned_steps

# Scene seeds: training scenes use parq-synth seed TRAIN_SEED, validation VALIDATION_SEED; the
# benchmark's held-out scenes use HELD_OUT_SEED.  Each scene's own seed is (seed, index), so
# the three ranges never share a scene.
TRAIN_SEED = 1000
VALIDATION_SEED = 2000
HELD_OUT_SEED = 3000

VIEWS = 3                   # views of a training snippet (data.load_scenes), the authors' 3
MAX_SEED = 2 ** 64 - 1      # torch.manual_seed takes seeds below 2**64
MAX_PROCESSES = 1024        # --jobs and --threads: more is a mistyped number (torch crashes)
DEMO_QUERIES = 64           # the demo's learned queries (--queries)
DEMO_IMAGE_SIZE = (160, 120)  # the demo's network input, width x height (--image-size)
# the paper's L1 center weight, loss.WEIGHTS["center"] (--center-weight); a copy, so that
# building the parser does not import torch (tests/test_train.py holds the two together)
PAPER_CENTER_WEIGHT = 5.0


# Argument types: a bad value is refused by the parser, before anything is generated.
seed = at_most(non_negative_int, MAX_SEED)
processes = at_most(positive_int, MAX_PROCESSES)
finite_positive_float = finite(positive_float)
finite_non_negative_float = finite(non_negative_float)


def checkpoint_file(text: str) -> pathlib.Path:
    """OUTPUT: a path whose last part is a file name (not empty, '.', '..' or ending in '/')."""
    if not text:
        raise argparse.ArgumentTypeError("the checkpoint path is empty")
    if text.replace(os.sep, "/").rsplit("/", 1)[-1] in ("", ".", ".."):
        raise argparse.ArgumentTypeError(f"{text} names a folder, expected a checkpoint file "
                                         "name (.pt)")
    return pathlib.Path(text)


def image_size(text: str) -> tuple:
    """--image-size WxH: a network input PARQConfig accepts (parq_export.config.image_size_fits)
    that parq-synth can render (at most parq_synth.scene.MAX_SIZE a side)."""
    from parq_export.config import IMAGE_MULTIPLE, MIN_IMAGE_SIDE, image_size_fits
    from parq_synth.scene import MAX_SIZE

    w, x, h = text.lower().partition("x")
    if not (x and w.isdigit() and h.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 192x144")
    w, h = int(w), int(h)
    if not image_size_fits(w, h) or max(w, h) > MAX_SIZE:
        raise argparse.ArgumentTypeError(f"{text}: width and height must be multiples of "
                                         f"{IMAGE_MULTIPLE} from {MIN_IMAGE_SIDE} to {MAX_SIZE}")
    return w, h


def given_path(text: str) -> pathlib.Path:
    """A path that is not empty (an empty one would be the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("the path is empty")
    return pathlib.Path(text)


def demo_config(**overrides):
    """The shipped demo model: ResNet18 at a quarter width, 128-channel features, 160x120,
    frames of other sizes point-sampled to it as parq-synth renders its training frames
    (parq_runtime.preprocess)."""
    from parq_export.config import PARQConfig

    base = dict(resnet_depth=18, resnet_width=16, fpn_channels=32, heads=4, ffn_dim=256,
                num_queries=DEMO_QUERIES, ray_samples=32, image_size=DEMO_IMAGE_SIZE, iterations=4,
                image_filter="point")
    base.update(overrides)
    return PARQConfig(**base)


def parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="parq-train", description=__doc__.splitlines()[0])
    p.add_argument("output", metavar="OUTPUT", type=checkpoint_file,
                   help="checkpoint to write (.pt), in an existing folder; written at the end "
                        "(to a temporary file renamed into place)")
    p.add_argument("--seed", type=seed, default=0,
                   help=f"training seed (0-{MAX_SEED}, default 0)")
    p.add_argument("--data", type=given_path, default=pathlib.Path("data/train"),
                   help="folder of training scenes, completed when scenes are missing; "
                        "scenes made with another --frames are an error (default data/train)")
    p.add_argument("--scenes", type=positive_int, default=1600,
                   help="training scenes: parq-synth scenes 0..N-1 of the training seed, the "
                        "missing ones generated into --data (default 1600)")
    p.add_argument("--jobs", type=processes, default=min(os.cpu_count() or 1, MAX_PROCESSES),
                   help="processes generating scenes (default: one per core)")
    p.add_argument("--frames", type=positive_int, default=30,
                   help="frames per training scene (default 30: more short scenes, not fewer "
                        "long ones, generalise better; see docs/demo-experiments.md)")
    p.add_argument("--pretrain-steps", type=non_negative_int, default=8000,
                   help="backbone pretraining steps on depth and object classes, the stand-in "
                        "for ImageNet weights (default 8000; 0 skips it)")
    p.add_argument("--pretrained", type=given_path, default=None,
                   help="start from this pretrained backbone instead of pretraining (the "
                        "OUTPUT stem + '-pretrained.pt' that every run with pretraining writes; "
                        "--pretrain-steps is then ignored): the same weights as pretraining "
                        "again with that file's steps and seed, without its minutes")
    p.add_argument("--steps", type=positive_int, default=19000,
                   help="PARQ training steps with the paper's objective (default 19000, the "
                        "demo's: 73 minutes on 2 AVX-512 EPYC cores)")
    p.add_argument("--minutes", type=finite_positive_float, default=None, metavar="M",
                   help="end the whole command (generation and pretraining included) within M "
                        f"minutes on this machine: after {PLAN_AT} training steps the run's "
                        "length is set to the most steps the minutes left hold at that pace "
                        f"plus 10%%, at most --steps, at least {MIN_STEPS}; the card records "
                        "the steps, and --steps with them repeats the run. Default: --steps, "
                        "however long it takes (the demo's 19000: 89 minutes on the AVX-512 "
                        "EPYC, about 140 on a 2-core AMX Xeon)")
    p.add_argument("--batch", type=positive_int, default=4, help="snippets per step (default 4)")
    p.add_argument("--gap", type=positive_int, default=1,
                   help="keyframes between a training snippet's views (default 1: consecutive, "
                        "as the authors); recorded in the model card, so parq-run forms its "
                        "snippets the same way")
    p.add_argument("--queries", type=positive_int, default=DEMO_QUERIES,
                   help="learned queries, the model's reference points (default 64, the "
                        "demo's; 128 cost 1.5 times a step and, trained for 12,500 steps, "
                        "scored 0.03 lower held out: see docs/demo-experiments.md)")
    p.add_argument("--image-size", type=image_size, default=DEMO_IMAGE_SIZE, metavar="WxH",
                   help="network input, width x height (default 160x120, the demo's); the "
                        "training scenes are rendered at this size, so each size needs its "
                        "own --data folder, and the pretraining runs at it. 192x144, trained "
                        "for the 13,000 steps the 90 minutes then allow, scored level with the "
                        "demo held out: see docs/demo-experiments.md")
    p.add_argument("--iterations", type=positive_int, default=4,
                   help="recurrent iterations supervised per step (default 4; 2 with 1.6x "
                        "the steps in the same minutes scored lower at 2 iterations, and its 4 "
                        "iterations no better than 1: see docs/demo-experiments.md)")
    p.add_argument("--lr", type=finite_positive_float, default=5e-4,
                   help="peak learning rate (default 5e-4; in the demo's recipe 1e-3 "
                        "diverged and 3e-4 scored level held out, lower on validation: see "
                        "docs/demo-experiments.md)")
    p.add_argument("--backbone-lr", type=finite_non_negative_float, default=1.0,
                   help="the pretrained ResNet-FPN's learning rate as a fraction of --lr "
                        "(default 1.0; 0 freezes it; 0.1 trained worse, see "
                        "docs/demo-experiments.md)")
    p.add_argument("--fused-attention", action="store_true",
                   help="torch's fused attention kernel in training: the same arithmetic in "
                        "another rounding order, 0.189 s a step at 2 threads against 0.215; "
                        "off by default so that the default command rebuilds the shipped demo "
                        "bit for bit (the demo's recipe with it, 20,000 steps, scored 0.032 "
                        "lower F1@0.25 held out: rounding alone moves a run that much, see "
                        "docs/demo-experiments.md)")
    p.add_argument("--bf16", action="store_true",
                   help="train (not pretrain) under bfloat16 autocast: on a Xeon with AMX a "
                        "step took 0.47 s at --batch 8 against 0.60 in float32 (0.26 against "
                        "0.31 at batch 4; benchmarks/train_step.py); without AMX bfloat16 is "
                        "emulated and slower. Neither run with it beat the demo's float32: 0.02 "
                        "lower F1@0.25 on 120 held-out scenes, level at IoU 0.5 "
                        "(benchmarks/results/spread-models.md); off by default")
    p.add_argument("--denoise", type=finite_non_negative_float, default=0.0, metavar="SCALE",
                   help="add one denoising query per target (DN-DETR; beyond the paper's "
                        "objective, training only: the exported graphs are the same), its "
                        "reference point the target's center moved by up to SCALE half "
                        "extents per axis (default 0: none, the paper's objective alone). "
                        "At 1.0 it raised reach but lowered F1, see docs/demo-experiments.md")
    p.add_argument("--denoise-class-weight", type=finite_non_negative_float, default=1.0,
                   metavar="W",
                   help="weight of the denoising queries' class loss against their box losses "
                        "(default 1.0; 0: boxes only, so that they cannot teach the class head "
                        "what the matching calls a duplicate)")
    p.add_argument("--mirror", action="store_true",
                   help="mirror augmentation: each training snippet is, with probability 1/2, "
                        "replaced by its mirror image (images flipped, the local frame "
                        "reflected; parq_train.mirror), twice the rooms for no extra time; "
                        "pretraining is unchanged. Off by default, so that the default command "
                        "rebuilds the shipped demo bit for bit")
    p.add_argument("--dense-weight", type=finite_non_negative_float, default=0.0, metavar="W",
                   help="add the pretraining's dense targets (per feature cell: log-depth and "
                        "the class seen there) as an auxiliary loss on the backbone's "
                        "features, through a linear probe dropped after training, times W "
                        "(beyond the paper's objective, training only: the exported graphs "
                        "are the same; parq_train.dense). Default 0: none, the paper's "
                        "objective alone")
    p.add_argument("--dropout", type=score, default=0.1, metavar="P",
                   help="train the decoder layer with dropout P on its residual branches and "
                        "FFN (training only: the exported graphs are the same; a step costs 3%% "
                        "more). Default 0.1, the authors' rate and the shipped demo's: +0.020 "
                        "F1@0.25 held out against 0, and 0.2 scored 0.07 lower on validation "
                        "(docs/demo-experiments.md)")
    p.add_argument("--attention-dropout", type=score, default=0.0, metavar="P",
                   help="dropout P on the decoder layer's attention weights, the authors' 0.1 "
                        "(training only; a step of the demo's configuration costs 1.5 times as "
                        "much with it). Default 0: none")
    p.add_argument("--key-dropout", type=score, default=0.0, metavar="P",
                   help="DropKey P on the cross-attention: each (query, cell) score dropped "
                        "before the softmax (beyond the authors' recipe; training only, the "
                        "exported graphs are the same; with --fused-attention a step took 0.229 "
                        "s against 0.189 without it and 0.299 with --attention-dropout 0.1 "
                        "instead, the demo's 0.215). Default 0: none (0.1 scored 0.039 lower "
                        "F1@0.25 held out: docs/demo-experiments.md)")
    p.add_argument("--center-weight", type=finite_non_negative_float,
                   default=PAPER_CENTER_WEIGHT, metavar="W",
                   help="weight of the L1 center loss against size 5, rotation 5 and class 1 "
                        "(the matching is unchanged). Default 5, the paper's and the shipped "
                        "demo's (10, in 3,000-step probes with two seeds, lowered the "
                        "validation center loss and moved F1@0.25 +0.044 and -0.061: "
                        "docs/demo-experiments.md)")
    p.add_argument("--average-from", type=non_negative_int, default=0, metavar="STEP",
                   help="write the mean of the weights after STEP, STEP + --average-every, "
                        "... steps up to the last (which must be on that grid) instead of the "
                        "last step's weights; the steps are the same (parq_train.average). "
                        "Default 0: the last weights (the demo's mean from 12000 scored "
                        "level with them held out, see docs/demo-experiments.md)")
    p.add_argument("--average-every", type=positive_int, default=2000, metavar="N",
                   help="steps between the weights --average-from counts (default 2000)")
    p.add_argument("--snapshot-every", type=non_negative_int, default=2000,
                   help="also write OUTPUT's stem + '-stepN.pt' every N training steps, and "
                        "the run's whole state to OUTPUT's stem + '-state.pt' for --resume "
                        "(removed when the run ends; 0: never; default 2000)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run from OUTPUT's stem + '-state.pt': give "
                        "the same command plus --resume; the weights come out as without the "
                        "interruption, bit for bit (parq_train.resume)")
    p.add_argument("--threads", type=processes, default=None,
                   help=f"torch threads (1-{MAX_PROCESSES}, default: all)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        return run(args, argv if argv is not None else sys.argv[1:])
    except ParqError as e:
        print(f"parq-train: error: {e}", file=sys.stderr)
        return 2


def check_arguments(args) -> None:
    """What the parser cannot check alone, before any work: the limits of parq-synth and the
    runtime, whether a scene's frames hold a snippet, and the outputs (:func:`check_outputs`).
    ParqError naming the flag or path."""
    from parq_export.export import MAX_QUERIES
    from parq_runtime.keyframes import span_of
    from parq_runtime.model_card import MAX_ITERATIONS
    from parq_synth.cli import MAX_FRAMES, MAX_SCENES

    for flag, value, limit in (("--scenes", args.scenes, MAX_SCENES),
                               ("--frames", args.frames, MAX_FRAMES),
                               ("--iterations", args.iterations, MAX_ITERATIONS),
                               ("--queries", args.queries, MAX_QUERIES)):
        if value > limit:
            raise ParqError(f"{flag} {value}: at most {limit}")
    span = span_of(VIEWS, args.gap)
    if span > args.frames:
        raise ParqError(f"--frames {args.frames}: a scene needs at least {span} frames for a "
                        f"snippet of {VIEWS} views {args.gap} keyframe(s) apart "
                        f"(--gap {args.gap})")
    if args.minutes is not None:
        if args.resume:
            raise ParqError("--minutes: not with --resume (a planned run's length is known "
                            "only after its first steps; resume it with --steps and the steps "
                            "its log planned)")
        if args.average_from:
            raise ParqError("--minutes: not with --average-from, whose steps must lie on a "
                            "grid ending at the last step")
        if args.steps < MIN_STEPS:
            raise ParqError(f"--minutes: --steps {args.steps} is below the {MIN_STEPS} a "
                            f"planned run needs (its warm-up must not depend on its length)")
    if args.average_from and (args.average_from > args.steps
                              or (args.steps - args.average_from) % args.average_every):
        raise ParqError(f"--average-from {args.average_from}: the last step (--steps "
                        f"{args.steps}) must be {args.average_from} plus a multiple of "
                        f"--average-every {args.average_every}")
    check_outputs(args)


def check_outputs(args) -> None:
    """OUTPUT and the files written beside it (the state, the pretrained backbone, the last
    snapshot) can be written (parq_runtime.files.check_writable: no folder, an existing
    folder that takes a file of that name).  ParqError naming the path."""
    from parq_runtime import files

    from .resume import path_for

    output = files.check_writable(args.output)
    beside = [path_for(output)]
    if args.pretrain_steps and args.pretrained is None:
        beside.append(pretrained_path(output))
    if args.snapshot_every and args.snapshot_every < args.steps:
        beside.append(snapshot_path(output, (args.steps - 1) // args.snapshot_every
                                    * args.snapshot_every))
    for path in beside:
        try:
            taken = path.is_dir()
        except OSError:     # a name too long once its ending is added: check_writable says so
            taken = False
        if taken:
            raise ParqError(f"{path}: is a folder, and parq-train writes this file beside "
                            f"{output}")
        files.check_writable(path)


def pretrained_path(output: pathlib.Path) -> pathlib.Path:
    return output.with_name(f"{output.stem}-pretrained.pt")


def snapshot_path(output: pathlib.Path, step: int) -> pathlib.Path:
    return output.with_name(f"{output.stem}-step{step}.pt")


def run(args, argv) -> int:
    began = time.perf_counter()     # --minutes counts from here
    check_arguments(args)

    import torch

    from parq_export import checkpoint

    from . import data, pretrain, resume, train
    from .symmetry import folds_of_class

    if args.threads:
        torch.set_num_threads(args.threads)
    config = demo_config(iterations=args.iterations, snippet_gap=args.gap,
                         num_queries=args.queries, image_size=args.image_size)
    command = "parq-train " + " ".join(argv)
    recipe = recipe_of(args)
    state_path = resume.path_for(args.output)
    state, earlier = resume.read(state_path, recipe) if args.resume else (None, None)
    if state is None and state_path.exists():
        print(f"parq-train: note: {state_path} is the state of an interrupted run, which "
              f"--resume would continue; this run starts over and replaces it", file=sys.stderr)
    saved = pretrain.read_backbone(args.pretrained, config) \
        if args.pretrained and state is None else None
    start = time.perf_counter()
    log = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    folders = data.training_scenes(args.data, args.scenes, TRAIN_SEED, args.frames,
                                   config.image_size, jobs=args.jobs, log=log)
    generated = time.perf_counter() - start
    snippets = data.load_scenes(folders, config, views=VIEWS, log=log,
                                dense=args.dense_weight > 0)
    if not snippets:
        raise ParqError(f"{args.data}: the {len(folders)} scenes of {args.frames} frames hold "
                        f"no snippet of {VIEWS} keyframes {args.gap} apart; lower --gap or "
                        f"raise --frames")
    if len(snippets) < args.batch:      # a step would silently take fewer
        raise ParqError(f"--batch {args.batch}: the {len(folders)} training scenes hold only "
                        f"{len(snippets)} snippets; lower --batch or raise --scenes")
    model = train.new_model(config, args.seed, snippets)
    pre_history, pre_record = [], {"steps": 0}
    if state is not None:
        pre_history, pre_record = earlier["pretrain_history"], earlier["pretraining"]
        log(f"resuming {state_path} at step {state['step']}/{args.steps}")
    elif saved:
        pretrain.set_backbone(model.backbone, saved[0], args.pretrained)
        pre_record = dict(saved[1], file=str(args.pretrained),
                          sha256=hashlib.sha256(args.pretrained.read_bytes()).hexdigest())
        log(f"backbone from {args.pretrained} ({pre_record['steps']} pretraining steps)")
    elif args.pretrain_steps:
        pre_history = pretrain.pretrain(model.backbone, config, folders, args.pretrain_steps,
                                        args.seed, log=log, log_every=500)
        pre_record = pretrain.record_of(
            config, args.pretrain_steps, args.seed, TRAIN_SEED, folders, args.frames,
            minutes=round((time.perf_counter() - start - generated) / 60, 1))
        path = pretrained_path(args.output)
        pretrain.save_backbone(path, model.backbone, pre_record)
        log(f"pretrained backbone {path}")
    pretrained = time.perf_counter() - start - generated
    if earlier is None:
        earlier = {"command": command, "resumed": [], "pretraining": pre_record,
                   "pretrain_history": pre_history,
                   "minutes": {"generate": round(generated / 60, 1),
                               "pretrain": round(pretrained / 60, 1)}}
    else:
        earlier = dict(earlier, resumed=earlier["resumed"] + [
            {"step": state["step"], "command": command, "at": now()}])

    def save_state(run_state):
        resume.save(state_path, run_state, recipe, earlier)

    budget_record = {}

    def plan(done, seconds):
        """--minutes: the run's length, from the pace of its first steps (budget.py)."""
        try:
            steps = planned_steps(args.minutes * 60, time.perf_counter() - began, done,
                                  seconds, args.steps)
        except ParqError as e:
            if args.pretrain_steps and args.pretrained is None:
                raise ParqError(f"{e} (the pretrained backbone is in "
                                f"{pretrained_path(args.output)}: --pretrained with it skips "
                                f"the pretraining)") from None
            raise
        log(f"--minutes {args.minutes:g}: {seconds / done:.3f} s a step over the first "
            f"{done}, so {steps} steps of at most {args.steps} (repeat with --steps {steps})")
        budget_record.update(minutes=args.minutes, most_steps=args.steps,
                             seconds_per_step=round(seconds / done, 4), planned_after=done)
        args.steps = recipe["steps"] = steps    # what the card and a saved state record
        return steps

    def snapshot(model_now, step):
        path = snapshot_path(args.output, step)
        checkpoint.save(path, model_now, {"step": step})
        log(f"snapshot {path}")

    model, history = train.train(config, snippets, args.steps, args.seed,
                                 folds_of_class(config.classes), batch_size=args.batch,
                                 iterations=args.iterations, lr=args.lr, log=log,
                                 log_every=250, model=model, snapshot=snapshot,
                                 snapshot_every=args.snapshot_every,
                                 backbone_lr=args.backbone_lr, form=attention_form(args),
                                 bf16=args.bf16,
                                 denoise_scale=args.denoise,
                                 denoise_class_weight=args.denoise_class_weight,
                                 mirror=args.mirror, dense_weight=args.dense_weight,
                                 average_from=args.average_from,
                                 average_every=args.average_every, dropout=args.dropout,
                                 attention_dropout=args.attention_dropout,
                                 key_dropout=args.key_dropout,
                                 center_weight=args.center_weight, state=state,
                                 save_state=save_state,
                                 plan=plan if args.minutes is not None else None,
                                 plan_at=PLAN_AT)
    trained = time.perf_counter() - start - generated - pretrained
    if state is not None:
        trained += state["seconds"]
    record = {"command": earlier["command"], "seed": args.seed,
              "data": {"generator": "parq-synth", "seed": TRAIN_SEED, "scenes": len(folders),
                       "frames": args.frames, "folder": str(args.data),
                       "snippets": len(snippets)},
              "pretrain_steps": pre_record["steps"], "pretraining": pre_record,
              **settings_record(args), **({"budget": budget_record} if budget_record else {}),
              "threads": torch.get_num_threads(),
              "minutes": dict(earlier["minutes"], train=round(trained / 60, 1)),
              "finished": now(),
              "torch": str(torch.__version__), "cpu_count": os.cpu_count(),
              "final_loss": history[-1] if history else None}
    if earlier["resumed"]:
        record["resumed"] = earlier["resumed"]
    model.config = model.config.replace(extra={"training": record})
    checkpoint.save(args.output, model, {"training": record, "history": history,
                                         "pretrain_history": pre_history})
    state_path.unlink(missing_ok=True)
    print(json.dumps(record, indent=1), file=sys.stderr)
    return 0


def settings_record(args) -> dict:
    """The training settings the model card records (``extra.training``), as it names them."""
    return {"steps": args.steps, "batch": args.batch,
            "iterations": args.iterations, "queries": args.queries, "gap": args.gap,
            "lr": args.lr, "backbone_lr": args.backbone_lr, "denoise": args.denoise,
            "denoise_class_weight": args.denoise_class_weight,
            "mirror_augment": args.mirror, "dense_weight": args.dense_weight,
            "attention": attention_form(args), "average": average_record(args),
            "dropout": args.dropout, "attention_dropout": args.attention_dropout,
            # only when set: the shipped card's record, made before the flag, has none
            **({"key_dropout": args.key_dropout} if args.key_dropout else {}),
            **({"center_weight": args.center_weight}
               if args.center_weight != PAPER_CENTER_WEIGHT else {}),
            "precision": "bfloat16 autocast" if args.bf16 else "float32"}


def attention_form(args) -> str:
    """PARQ.forward's attention form in training."""
    return "fused" if args.fused_attention else "cached"


def recipe_of(args) -> dict:
    """The settings a resumed run must repeat: all that decide the weights (not the output
    path, data folder, processes, threads or snapshot cadence)."""
    return {"seed": args.seed, "scenes": args.scenes, "frames": args.frames,
            "pretrain_steps": args.pretrain_steps,
            "pretrained": str(args.pretrained) if args.pretrained else None,
            "steps": args.steps, "batch": args.batch, "gap": args.gap,
            "iterations": args.iterations, "lr": args.lr, "backbone_lr": args.backbone_lr,
            "fused_attention": args.fused_attention, "bf16": args.bf16,
            "denoise": args.denoise, "denoise_class_weight": args.denoise_class_weight,
            "mirror": args.mirror,
            # only when set, so that the states of runs from before the flags still resume
            **({"dense_weight": args.dense_weight} if args.dense_weight else {}),
            **({"average": average_record(args)} if args.average_from else {}),
            **({"dropout": args.dropout} if args.dropout else {}),
            **({"attention_dropout": args.attention_dropout} if args.attention_dropout else {}),
            **({"key_dropout": args.key_dropout} if args.key_dropout else {}),
            **({"center_weight": args.center_weight}
               if args.center_weight != PAPER_CENTER_WEIGHT else {}),
            **({"queries": args.queries} if args.queries != DEMO_QUERIES else {}),
            # always, so that a change of the default cannot resume a run at another size
            # (states written before the flag, at 160x120, hold none: they no longer resume)
            "image_size": list(args.image_size)}


def average_record(args) -> dict | None:
    """The weight mean a run writes (None: its last weights): the steps it counts."""
    if not args.average_from:
        return None
    return {"from": args.average_from, "every": args.average_every,
            "count": (args.steps - args.average_from) // args.average_every + 1}


def now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


if __name__ == "__main__":
    sys.exit(main())
