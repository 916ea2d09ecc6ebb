"""parq-run: detect 3D boxes in a folder of posed frames."""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

from .arguments import (OneLineParser, floor_height, match_iou, non_negative_float, positive_int,
                        ray_ratio, scene_nms, score)
from .errors import ParqError
from .files import os_error

DEFAULT_MODEL = pathlib.Path(__file__).resolve().parents[1] / "models" / "parq-demo"


def parser() -> argparse.ArgumentParser:
    from .fusion import LABEL_RULES, MODES
    from .gravity import CHOICES
    from .readers import FORMATS

    p = OneLineParser(
        prog="parq-run",
        description="Detect 3D boxes in a folder of posed RGB frames with an exported PARQ "
                    "model: keyframes -> snippets -> detections -> scene fusion, as JSON.")
    p.add_argument("frames", type=pathlib.Path,
                   help="capture folder: a ScanNet export (color/, pose/, intrinsic/), "
                        "ARKitScenes raw (lowres_wide/, lowres_wide.traj), the demo's "
                        "fragments.pkl + images/, a nerfstudio transforms.json or a COLMAP "
                        "text model (see docs/readers.md)")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="read the folder as this layout (default: detected from its files)")
    p.add_argument("--up", choices=CHOICES, default=None,
                   help="the world's up axis (default: the format's convention, +z for "
                        "ScanNet, ARKitScenes and the demo layout; estimated from the cameras "
                        "for COLMAP and nerfstudio); auto estimates it from the cameras. "
                        "Write a negative axis with '=': --up=-y")
    p.add_argument("--model", type=pathlib.Path,
                   default=pathlib.Path(os.environ.get("PARQ_MODEL", DEFAULT_MODEL)),
                   help="model folder written by parq-export (default: $PARQ_MODEL or "
                        "the shipped demo model, models/parq-demo)")
    p.add_argument("--iters", type=positive_int, default=None,
                   help="recurrent iterations per snippet (default: the model card's run "
                        "setting, 2 for the demo and the authors' checkpoints; more is slower "
                        "and usually more accurate)")
    p.add_argument("--queries", type=positive_int, default=None,
                   help="number of queries (reference points) per snippet (default: the "
                        "model card's run setting, 64 for the demo, 32 for the authors' "
                        "checkpoints; fewer is faster)")
    p.add_argument("--views", type=positive_int, default=3,
                   help="keyframes per snippet (default 3, as the authors train)")
    p.add_argument("--stride", type=positive_int, default=None,
                   help="keyframes between snippet starts (default: --views, no overlap)")
    p.add_argument("--gap", type=positive_int, default=None,
                   help="keyframes between a snippet's views (default: the model card's; 1, "
                        "consecutive keyframes, for the authors' checkpoints)")
    p.add_argument("--score-threshold", type=score, default=None,
                   help="keep boxes scoring above this (default: the model card's, 0.8 for "
                        "the authors' checkpoints)")
    p.add_argument("--all-regions", action="store_true",
                   help="keep boxes anywhere; by default only centers inside the authors' "
                        "evaluation region of each snippet are kept")
    p.add_argument("--fusion", choices=MODES, default=None,
                   help="scene box from the snippets' matched detections: best = the highest "
                        "score (the authors' protocol), mean = its class and rotation with the "
                        "score-weighted mean center and size, ray = as mean but each center "
                        "trusted less along its viewing ray than across it (default: the "
                        "model card's)")
    p.add_argument("--labels", choices=LABEL_RULES, default=None,
                   help="class of a scene box: best = its best-scoring detection's (the "
                        "authors' protocol), vote = the class whose detections' scores sum "
                        "highest over its snippets (default: the model card's)")
    p.add_argument("--ray-ratio", type=ray_ratio, default=None,
                   help="for --fusion ray: how many times less a detection's depth along its "
                        "viewing ray is trusted than its position across it (>= 1; 1 is "
                        "mean; default: the model card's)")
    p.add_argument("--scene-nms", type=scene_nms, default=None, metavar="IOU|off",
                   help="report one scene box per object: of two scene boxes of one class "
                        "overlapping by more than this IoU, only the better-scoring; 'off' "
                        "reports both, as the authors' protocol (default: the model card's)")
    p.add_argument("--match-iou", type=match_iou, default=None, metavar="IOU",
                   help="a snippet's detection joins the scene box it overlaps most when their "
                        "3D IoU is at least this, in (0, 1]; lower joins more of one small "
                        "object's detections into one box (default: the model card's; the "
                        "authors' 0.1)")
    p.add_argument("--floor", type=floor_height, default=None, metavar="HEIGHT|off",
                   help="the floor's height along the world's up axis in metres, when known "
                        "(an AR session's floor plane, say); with ray fusion, boxes of the "
                        "card's floor classes are pulled to stand on it. 'off': no floor "
                        "prior. Default: found in the images by a plane sweep when the card "
                        "names floor classes (none found: no prior)")
    p.add_argument("--min-support", type=positive_int, default=None,
                   help="report a scene box only when at least this many snippets detect it "
                        "(runs, with mirror runs: two a snippet; default: the model card's, "
                        "scaled to the runs a snippet gets; 1 for the authors' checkpoints)")
    p.add_argument("--mirror", action=argparse.BooleanOptionalAction, default=None,
                   help="also run each snippet on its mirror image (frames flipped left-right, "
                        "the world reflected) and fuse both runs' boxes: twice the time, "
                        "support then counts runs (default: the model card's run setting, on "
                        "for the demo, off for the authors' checkpoints; --no-mirror for half "
                        "the time)")
    p.add_argument("--phases", type=int, choices=(1, 2), default=None,
                   help="point-sampling grids each snippet is run at, for frames at least "
                        "twice the network size each way with a card that point-samples: 2 "
                        "adds a run on the pixels half a network pixel over (and its mirror "
                        "run), twice the time; smaller frames have one grid (default: the "
                        "model card's run setting, 1 for the demo: no gain held out)")
    p.add_argument("--form", choices=("auto", "cached", "folded"), default="auto",
                   help="cross-attention form: auto picks the cheaper exact one (default)")
    p.add_argument("--keyframe-angle", type=non_negative_float, default=15.0,
                   help="degrees of turn that make a new keyframe (default 15)")
    p.add_argument("--keyframe-distance", type=non_negative_float, default=0.1,
                   help="metres of motion that make a new keyframe (default 0.1)")
    p.add_argument("--max-snippets", type=positive_int, default=None,
                   help="stop after this many snippets (a quick look)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="onnxruntime intra-op threads (default: one per core)")
    p.add_argument("--providers", default=None,
                   help="comma-separated onnxruntime execution providers, e.g. "
                        "CUDAExecutionProvider (default: CPU)")
    p.add_argument("-o", "--output", type=pathlib.Path, default=None,
                   help="write the JSON here (written whole or not at all) instead of stdout")
    p.add_argument("--vis", type=pathlib.Path, default=None, metavar="DIR",
                   help="also draw each snippet's boxes (solid, labelled) and the fused scene "
                        "boxes (dashed) on its keyframes, as PNGs in this folder (written "
                        "whole or not at all; an earlier --vis folder is replaced)")
    p.add_argument("--ply", type=pathlib.Path, default=None, metavar="FILE",
                   help="also write the scene boxes as coloured wireframes (PLY, world frame) "
                        "for MeshLab, Open3D or CloudCompare")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress, notes or summary "
                   "on stderr (warnings are still printed)")
    return p


class Progress:
    """A progress line on stderr: redrawn in place on a terminal, every 10% otherwise."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self.last = -1

    def __call__(self, done: int, total: int):
        if not self.enabled or total == 0:
            return
        tenth = 10 * done // total
        if self.tty:
            bar = "#" * (30 * done // total)
            print(f"\r[{bar:30s}] {done}/{total} snippets", end="", file=sys.stderr,
                  flush=True)
            if done == total:
                print(file=sys.stderr)
        elif tenth != self.last:
            print(f"{done}/{total} snippets", file=sys.stderr, flush=True)
        self.last = tenth


def check_outputs(args) -> None:
    from . import files, visualize

    paths = [p for p in (args.output, args.ply) if p is not None]
    for path in paths:
        files.check_writable(path)
    # resolved, so that a/../x and x (or a link to it) are seen to be the same path
    if len(paths) == 2 and paths[0].resolve() == paths[1].resolve():
        raise ParqError(f"{paths[0]}: given for both -o and --ply")
    if args.vis is not None:
        visualize.check_output(args.vis)
        for path in paths:
            if args.vis.resolve() == path.resolve():
                raise ParqError(f"{path}: given for both --vis and a file output")


def run(args) -> int:
    from . import files, ply, readers, results, scene, visualize
    from .detector import MAX_ITERATIONS, Detector

    if args.iters is not None and args.iters > MAX_ITERATIONS:
        raise ParqError(f"--iters {args.iters}: at most {MAX_ITERATIONS}")
    check_outputs(args)
    capture = readers.open_capture(args.frames, args.format, args.up)
    for warning in capture.warnings:
        print(f"parq-run: warning: {warning}", file=sys.stderr)
    detector = Detector(args.model, providers=args.providers, threads=args.threads)
    if args.views > detector.card.max_views:
        raise ParqError(f"--views {args.views}: this model takes at most "
                        f"{detector.card.max_views} views per snippet")
    settings = scene.RunSettings(
        iters=args.iters, queries=args.queries, views=args.views, stride=args.stride,
        gap=args.gap,
        score_threshold=args.score_threshold, region=not args.all_regions, form=args.form,
        keyframe_angle=args.keyframe_angle, keyframe_distance=args.keyframe_distance,
        max_snippets=args.max_snippets, fusion=args.fusion, min_support=args.min_support,
        ray_ratio=args.ray_ratio, scene_nms=args.scene_nms, mirror=args.mirror,
        phases=args.phases, floor=args.floor, labels=args.labels, match_iou=args.match_iou)
    settings = scene.resolved(settings, detector.card)      # the card's iters / queries
    detector.reference_points(settings.queries)  # argument check before the long part
    keys, snippets = scene.plan(capture, settings, detector.card)
    if not snippets:
        gap = scene.snippet_gap(settings, detector.card)
        spacing = f" {gap} keyframes apart" if gap > 1 else ""
        raise ParqError(f"{args.frames}: {len(capture.frames)} frames give {len(keys)} "
                        f"keyframes, fewer than one snippet of {args.views} views{spacing}")
    used = sorted({i for snippet in snippets for i in snippet})
    readers.check_headers(capture.frames[i] for i in used)   # fail before the long part
    result = scene.run(detector, capture, settings, Progress(not args.quiet))
    threshold = detector.card.score_threshold if args.score_threshold is None \
        else args.score_threshold
    text = json.dumps(results.to_json(result, settings, detector.card, threshold), indent=1)
    with files.staged_files() as stage:     # -o, --ply and --vis: all of them or none
        if args.output is not None:
            stage(args.output, text + "\n")
        if args.ply is not None:
            stage(args.ply, ply.ply_text(result.fusion.boxes))
        images = visualize.write(result, args.vis) if args.vis is not None else 0
    if args.output is None:
        files.write_stdout(text)
    if not args.quiet:
        for note in capture.notes:      # after the run: an error stays a single line
            print(f"parq-run: note: {note}", file=sys.stderr)
        if result.floor is not None:
            where = "given" if result.floor["source"] == "given" else "found in the images"
            print(f"parq-run: note: floor at {result.floor['height']:+.3f} m along up "
                  f"({where}); {', '.join(result.fusion.floor_classes)} stand on it",
                  file=sys.stderr)
        elif result.fusion.floor_classes:
            print("parq-run: note: no floor found in the images near the boxes' bottoms; no "
                  "box was pulled to one", file=sys.stderr)
        extra = f", {images} images in {args.vis}" if args.vis is not None else ""
        where = f" -> {args.output}" if args.output is not None else ""
        print(f"parq-run: {len(result.snippets)} snippets, {len(result.fusion.boxes)} scene "
              f"boxes, {result.seconds:.1f} s{extra}{where}", file=sys.stderr)
        if args.output is not None:     # JSON went to a file: show the boxes here
            for line in results.summary_lines(result.fusion.boxes):
                print(line, file=sys.stderr)
    return 0


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        return run(args)
    except ParqError as e:
        print(f"parq-run: error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:    # a path the checks could not foresee (permissions, /proc)
        print(f"parq-run: error: {os_error(e)}", file=sys.stderr)
        return ParqError.exit_code
    except KeyboardInterrupt:
        print("parq-run: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
