"""The demo on frames rendered larger than its input: the resize filter, softness or geometry.

parq-synth's renderer does not antialias (a pixel is its centre ray), and the demo was
trained on frames rendered at its own 160x120. Frames rendered at 320x240 reach it through
parq-run's resize, with the filter the model card names (parq_runtime.preprocess): Pillow's
bilinear filter, antialiased when it shrinks (the authors'), is softer than anything the demo
trained on; point sampling takes the pixel whose ray the scaled intrinsics name, as sharp as
its training frames and exact geometry at this whole-number ratio. This script runs the model
on the same held-out rooms four ways, paired over 10,000 resamples of the scenes (spread.py):

* rendered at 160x120 (the documented numbers);
* rendered at 320x240, resized by parq-run with Pillow's filter (image.filter
  "pillow-bilinear");
* rendered at 320x240, point-sampled by parq-run (image.filter "point");
* rendered at 320x240 and resized here with Pillow's filter, but with the intrinsics of the
  pixel-centre convention, c' = (c + 0.5) / 2 - 0.5. parq-run scales the intrinsics' rows by
  the size ratio (the authors' rule, c' = c / 2), which puts the principal point a quarter
  pixel off the grid Pillow resamples to; this arm has the softness without that quarter
  pixel.

The two parq-run arms use copies of the model folder that differ from it only in
image.filter (parq_export.card_rewrite), written to benchmarks/.cache/; the derived scenes of
the last arm to benchmarks/.cache/<folder of the 320x240 scenes>_resized (colour, poses,
intrinsics, boxes).
A deficit in both Pillow arms and none point-sampled means the cost at 320x240 is the
softness of the resize, not the geometry.

    python benchmarks/resize_softness.py --scenes 120 --out benchmarks/results/resize_softness
    python benchmarks/resize_softness.py --seed 5000 --scenes 120  # a fresh held-out set

or on any two folders holding the same rooms rendered at 160x120 and at 320x240 (the
validation scenes the demo card's filter was chosen on, say; the ground truth is checked to
be the same scene by scene):

    parq-synth data/val320 --scenes 40 --seed 2000 --frames 60 --jobs 2
    python benchmarks/resize_softness.py --pair data/val data/val320 \
        --out benchmarks/results/resize_softness-val
"""
from __future__ import annotations

import argparse
import pathlib
import shutil

import numpy as np
from PIL import Image

import common
import spread
import tradeoff

LABELS = ("rendered at 160x120", "rendered at 320x240, parq-run with Pillow's filter",
          "rendered at 320x240, parq-run point-sampling",
          "rendered at 320x240, Pillow's filter, pixel-centre intrinsics")


def halved(large: pathlib.Path, out: pathlib.Path) -> pathlib.Path:
    """A copy of scene folder ``large`` with every colour frame halved in size by Pillow's
    bilinear filter, principal point (c + 0.5) / 2 - 0.5; depth and masks are not copied
    (parq-run does not read them). Written once."""
    if (out / "boxes.json").exists():
        return out
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "color").mkdir(parents=True)
    for frame in sorted((large / "color").glob("*.png")):
        image = Image.open(frame)
        image.resize((image.width // 2, image.height // 2), Image.BILINEAR).save(
            tmp / "color" / frame.name)
    shutil.copytree(large / "pose", tmp / "pose")
    (tmp / "intrinsic").mkdir()
    K = np.loadtxt(large / "intrinsic" / "intrinsic_color.txt")
    K[:2] /= 2
    K[:2, 2] -= 0.25
    np.savetxt(tmp / "intrinsic" / "intrinsic_color.txt", K)
    shutil.copy(large / "intrinsic" / "extrinsic_color.txt", tmp / "intrinsic")
    for name in ("scene.json", "boxes.json"):
        shutil.copy(large / name, tmp / name)
    tmp.rename(out)
    return out


def with_filter(model: pathlib.Path, name: str) -> pathlib.Path:
    """A copy of model folder ``model`` whose card names resize filter ``name``, written to
    the cache (again each run: the source may have changed)."""
    from parq_export import card_rewrite
    from parq_export.export import RESIZE_TEXT

    def update(card):
        card["image"].update(filter=name, resize=RESIZE_TEXT[name])
        card["config"]["image_filter"] = name
    out = common.CACHE / f"resize_softness_{name}"
    card_rewrite.rewrite(model, out, update, overwrite=True)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    tradeoff.add_scene_arguments(p, "run")
    p.add_argument("--pair", nargs=2, type=pathlib.Path, metavar=("SMALL", "LARGE"),
                   help="instead of held-out scenes: two folders of scenes, the same rooms "
                        "rendered at 160x120 and at 320x240")
    p.add_argument("--out", default=str(common.RESULTS / "resize_softness"),
                   help="output stem: .md and .json (default results/resize_softness)")
    args = p.parse_args()
    if args.size != "160x120":
        raise SystemExit("resize_softness: --size is 160x120 here (and 320x240 beside it)")

    from parq_runtime import Detector

    if args.pair:
        native, large = ([f.parent for f in sorted(folder.glob("*/boxes.json"))]
                         for folder in args.pair)
        if not native or [f.name for f in native] != [f.name for f in large]:
            raise SystemExit(f"resize_softness: --pair {args.pair[0]} {args.pair[1]}: not "
                             "the same scenes in both (or none)")
        for scenes, size in ((native, (160, 120)), (large, (320, 240))):
            first = min((scenes[0] / "color").glob("*.png"))
            if Image.open(first).size != size:
                raise SystemExit(f"resize_softness: {first}: not {size[0]}x{size[1]}")
        where = f"{len(native)} scenes of {args.pair[0]} and {args.pair[1]}"
    else:
        native, _ = tradeoff.scenes_from_arguments(args)
        args.size = "320x240"
        large, _ = tradeoff.scenes_from_arguments(args)
        where = tradeoff.held_out_text(args).replace(", 320x240)", ")")
    resized = [halved(f, common.CACHE / f"{f.parent.resolve().name}_resized" / f.name)
               for f in large]
    model = pathlib.Path(args.model).resolve()
    card = Detector(model)
    detectors = [card, Detector(with_filter(model, "pillow-bilinear")),
                 Detector(with_filter(model, "point")), card]
    model = model.relative_to(common.ROOT) if model.is_relative_to(common.ROOT) else model
    arms = (native, large, large, resized)
    classes = detectors[0].classes
    truth = spread.truth_counts(native, classes)
    if any(not np.array_equal(spread.truth_counts(s, classes), truth) for s in arms[1:]):
        raise SystemExit("resize_softness: the renders hold different ground truth")
    iters, queries = detectors[0].card.run_setting(None, None)
    counts = [spread.scene_counts(d, scenes, iters, queries)
              for d, scenes in zip(detectors, arms)]
    rows = spread.spread(counts, 10000, 40)
    lines = [f"{model} at {iters} x {queries}"
             f"{', mirror runs' if detectors[0].card.run_mirror else ''}, on "
             f"{where}, the same rooms rendered at two sizes; 90% intervals and paired "
             "differences from 10,000 resamples of the scenes.", "",
             "| frames | F1@0.25 | vs 160x120, paired | F1@0.5 | vs 160x120, paired |",
             "|---|---|---|---|---|"]
    for label, row in zip(LABELS, rows):
        lines.append("| " + " | ".join([label] + spread.paired_cells(row)) + " |")
    common.write_report(pathlib.Path(args.out), lines, {
        "model": str(model), "scenes": len(native),
        "source": [str(f) for f in args.pair] if args.pair else {"seeds": args.seed},
        "setting": {"iters": iters, "queries": queries, "mirror": detectors[0].card.run_mirror},
        "frames": list(LABELS), "rows": rows,
        "scene_counts": {label: c.tolist() for label, c in zip(LABELS, counts)}})


if __name__ == "__main__":
    main()
