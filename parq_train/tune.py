"""Choose a trained model's post-processing on validation scenes: score threshold, the local
evaluation region (which snippet detections are kept before scene fusion), and the scene
fusion (mode, minimum support and, for ``ray`` fusion, the ray ratio; parq_runtime.fusion).

The authors fixed both for ScanNet (score > 0.8; centers with |x| < 1.5 m and z < 2 m in the
snippet frame).  A model trained here scores on a different scale and sees different rooms,
so the demo picks them on validation scenes (parq-synth seeds 2000 and 2001, never trained
on, never used for the reported numbers; ``--data`` pools several folders): the candidate that
maximises F1@0.25 + F1@0.5 at the run setting given (``--iters``, ``--queries``), or with
``--min-f1-50 F`` the best F1@0.25 among the candidates whose F1@0.5 is at least F
(:class:`Criterion`); ties go to the authors' fusion (best, support 1).  That setting is
written to the card as the one parq-run uses when not told (``run``), so the default run is
the one the post-processing was chosen for.

The search, pass by pass, is parq_train.postprocess_search; the detector's pass over the
validation scenes that it scores is parq_train.validation_runs.  This module is the command.

Before the search, a checkpoint's learned queries are ranked (``query_order``, see
parq_runtime.queries; a model folder keeps its own ranking): one pass with all of them, each
query scored by the snippet detections it makes above score 0.7, +1 for each that overlaps a
ground-truth box of its class at IoU 0.25 and -0.5 for each that does not.  Runs with fewer
queries start from the best ones, and the post-processing is chosen for that subset.

    python -m parq_train.tune work/demo.pt --data data/val data/val2 --queries 64 \
        -o work/demo-tuned.pt
    python -m parq_train.tune models/parq-demo --data data/val data/val2 --queries 64 \
        --mirror -o work/parq-demo-tuned

Given a checkpoint it writes a checkpoint (parq-export it next).  Given an exported model
folder it writes a copy of the folder whose card (and the graphs' mirrored cards) hold the
new choice; the folder's query order is kept, so the same weights give the same card either
way when the folder's order is what tuning its checkpoint ranked.
"""
from __future__ import annotations

import json
import os
import pathlib
import sys
import tempfile

from parq_runtime.arguments import OneLineParser, fraction, positive_int
from parq_runtime.errors import ParqError
from parq_train.postprocess_search import AUTHORS, CHOSEN, Criterion, choose, select_phases
from parq_train.validation_runs import (FALSE_WEIGHT, RANKING_IOU, RANKING_SCORE,
                                        check_two_grids, floor_sweep, query_utility,
                                        rank_queries, run_looks, run_once, validation_folders)


def main(argv=None) -> int:
    # the docstring's first paragraph: its first line alone stops mid-sentence
    p = OneLineParser(prog="python -m parq_train.tune",
                      description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("checkpoint", type=pathlib.Path,
                   help="trained checkpoint (parq-train), or a model folder (parq-export)")
    p.add_argument("--data", type=pathlib.Path, nargs="+", default=[pathlib.Path("data/val")],
                   help="one or more folders of validation scenes, pooled (default data/val: "
                        "parq-synth seed 2000)")
    p.add_argument("--scenes", type=positive_int, default=None,
                   help="use the first N scenes of each --data folder (default: all)")
    p.add_argument("--iters", type=positive_int, default=2,
                   help="iterations to choose the post-processing for; the card records them "
                        "as parq-run's default (default 2)")
    p.add_argument("--queries", type=positive_int, default=32,
                   help="queries to choose the post-processing for; the card records them as "
                        "parq-run's default (default 32; the demo's 64)")
    p.add_argument("--mirror", action="store_true",
                   help="choose the post-processing for runs that add each snippet's mirror "
                        "image (parq-run --mirror; supports up to 4 runs); the card records "
                        "mirror runs as parq-run's default")
    p.add_argument("--phase-data", type=pathlib.Path, nargs="+", default=None, metavar="DIR",
                   help="also choose whether parq-run adds the second point-sampling grid "
                        "(--phases 2) and its support, on these validation scenes rendered at "
                        "least twice the network size each way (the --data scenes at 320x240 "
                        "for the demo); model folders only (default: not chosen, one grid)")
    p.add_argument("--min-f1-50", type=fraction, default=None, metavar="F",
                   help="choose the candidate with the best F1@0.25 among those whose F1@0.5 "
                        "on the validation scenes is at least F (default: the best F1@0.25 + "
                        "F1@0.5)")
    p.add_argument("--jobs", type=positive_int, default=os.cpu_count() or 1,
                   help="processes that score the candidates (default: one per core; the "
                        "choice is the same for any number)")
    p.add_argument("-o", "--output", type=pathlib.Path, required=True,
                   help="checkpoint to write with the chosen post-processing (for a model "
                        "folder: the new model folder, which must not exist)")
    args = p.parse_args(argv)
    try:
        return run(args)
    except ParqError as e:
        print(f"parq_train.tune: error: {e}", file=sys.stderr)
        return 2


def criterion_of(args) -> Criterion:
    """The :class:`Criterion` that ``args`` (main's) ask for."""
    return Criterion(args.min_f1_50)


def record_of(args, folders, best, table, ranking) -> dict:
    """What the card's ``extra.postprocess_tuning`` says about a tuning run."""
    authors = next(r for r in table if all(r[k] == v for k, v in AUTHORS.items()))
    seeds = sorted({json.loads((f / "scene.json").read_text()).get("seed") for f in folders
                    if (f / "scene.json").exists()})
    return {"data": [str(d) for d in args.data], "seeds": seeds, "scenes": len(folders),
            "iters": args.iters, "queries": args.queries, "mirror": args.mirror,
            "criterion": criterion_of(args).describe(),
            "chosen": best, "authors_settings": authors, "query_ranking": ranking}


def run(args) -> int:
    folders = validation_folders(args.data, args.scenes)
    if args.checkpoint.is_dir():
        return run_folder(args, folders)
    return run_checkpoint(args, folders)


def run_folder(args, folders) -> int:
    """Tune an exported model folder; writes a copy with the new card (module doc)."""
    from parq_export import card_rewrite
    from parq_runtime import Detector

    detector = Detector(args.checkpoint)
    if args.output.exists():
        raise ParqError(f"{args.output}: already exists (a model folder is written new)")
    phase_folders = validation_folders(args.phase_data, args.scenes) if args.phase_data else []
    check_two_grids(phase_folders, detector.card)
    records = run_once(detector, folders, args.iters, args.queries, mirror=args.mirror)
    best, table = choose(records, detector.classes, floor_sweep(folders), args.mirror,
                         args.jobs, criterion_of(args))
    phases, phase_support = 1, None
    if phase_folders:
        looks = run_looks(detector, phase_folders, args.iters, args.queries, args.mirror)
        (phases, phase_support), phase_rows = select_phases(
            looks, detector.classes, best, floor_sweep(phase_folders), args.mirror,
            criterion_of(args))
        table += phase_rows
    previous = detector.card.raw.get("extra", {}).get("postprocess_tuning") or {}
    ranking = previous.get("query_ranking")
    if ranking:
        ranking = dict(ranking, kept_from=str(args.checkpoint))
    record = dict(record_of(args, folders, best, table, ranking),
                  tuned=f"model folder {args.checkpoint}", phases=phases,
                  phase_support=phase_support,
                  phase_data=[str(d) for d in args.phase_data or ()])

    def update(card):
        card["postprocess"].update({k: best[k] for k in CHOSEN}, phase_support=phase_support)
        card["run"] = {"iters": args.iters, "queries": args.queries, "mirror": args.mirror,
                       "phases": phases}
        card["extra"] = dict(card.get("extra", {}), postprocess_tuning=record)
    card_rewrite.rewrite(args.checkpoint, args.output, update)
    print(json.dumps(record, indent=1))
    return 0


def run_checkpoint(args, folders) -> int:
    from parq_export import checkpoint
    from parq_export.export import export
    from parq_runtime import Detector

    if args.phase_data:
        raise ParqError("--phase-data chooses for a model folder: export the checkpoint, then "
                        "tune the folder")

    loaded = checkpoint.load(args.checkpoint)
    learned = loaded.config.num_queries
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        export(args.checkpoint, tmp / "model", log=lambda *_: None)
        detector = Detector(tmp / "model")
        # the ranking is recorded whatever --queries is, so that a run with fewer queries
        # than the card's setting starts from the best ones
        records = run_once(detector, folders, args.iters, learned)
        utility = query_utility(records, learned)
        order = rank_queries(utility)
        ranking = {"utility": [float(u) for u in utility], "order": order,
                   "criterion": f"snippet detections above {RANKING_SCORE}: +1 if IoU >= "
                                f"{RANKING_IOU} with a box of its class, else "
                                f"-{FALSE_WEIGHT}", "iters": args.iters}
        if args.queries < learned:
            ranked = loaded.model()
            ranked.config = loaded.config.replace(query_order=tuple(order))
            checkpoint.save(tmp / "ranked.pt", ranked, {})
            export(tmp / "ranked.pt", tmp / "ranked", log=lambda *_: None)
            detector = Detector(tmp / "ranked")
        if args.queries != learned or args.mirror:
            records = run_once(detector, folders, args.iters, args.queries,
                               mirror=args.mirror)
        classes = detector.classes
    best, table = choose(records, classes, floor_sweep(folders), args.mirror, args.jobs,
                         criterion_of(args))
    record = record_of(args, folders, best, table, ranking)
    model = loaded.model()
    extra = dict(loaded.config.extra, postprocess_tuning=record)
    chosen = {k: tuple(best[k]) if isinstance(best[k], list) else best[k] for k in CHOSEN}
    model.config = loaded.config.replace(
        **chosen, run_iters=args.iters, run_queries=args.queries, run_mirror=args.mirror,
        extra=extra, query_order=tuple(order))
    metadata = {"tuning_table": table}
    checkpoint.save(args.output, model, metadata)
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
