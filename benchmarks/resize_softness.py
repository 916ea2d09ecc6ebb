"""Why the demo scores lower on frames rendered larger than its input: softness or geometry.

parq-synth's renderer does not antialias (a pixel is its centre ray), and the demo was
trained on frames rendered at its own 160x120. Frames rendered at 320x240 reach it through
parq-run's resize (Pillow's bilinear filter, antialiased when it shrinks, as the authors'
pipeline), softer than anything it trained on. This script runs the model card on the same
held-out rooms three ways, paired over 10,000 resamples of the scenes (spread.py):

* rendered at 160x120 (the documented numbers);
* rendered at 320x240 and resized by parq-run (softer frames);
* rendered at 320x240 and point-sampled to 160x120, every second pixel of every second row,
  with the intrinsics halved. Pixel (u, v) of that frame is pixel (2u, 2v) of the large one,
  whose ray is exactly what the halved intrinsics say: as sharp as the model's training
  frames, and exact geometry;
* rendered at 320x240 and resized here with parq-run's own filter, but with the intrinsics
  of the pixel-centre convention, c' = (c + 0.5) / 2 - 0.5. parq-run scales the intrinsics'
  rows by the size ratio (the authors' rule, c' = c / 2), which puts the principal point a
  quarter pixel off the grid Pillow resamples to; this arm has the softness without that
  quarter pixel.

Level point-sampled frames and a deficit in both resized arms mean the cost at 320x240 is the
softness of the resize, not the geometry. The derived scenes are written once to
benchmarks/.cache/held_out_320x240_pointsampled and _resized (colour, poses, intrinsics,
boxes).

    python benchmarks/resize_softness.py --scenes 120 --out benchmarks/results/resize_softness
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

LABELS = ("rendered at 160x120", "rendered at 320x240, resized by parq-run",
          "rendered at 320x240, point-sampled to 160x120",
          "rendered at 320x240, resized, pixel-centre intrinsics")


def halved(large: pathlib.Path, out: pathlib.Path, how: str) -> pathlib.Path:
    """A copy of scene folder ``large`` with every colour frame halved in size, ``how``
    "point" (pixel (2u, 2v), intrinsics halved) or "resize" (Pillow's bilinear filter,
    principal point (c + 0.5) / 2 - 0.5); depth and masks are not copied (parq-run does not
    read them). Written once."""
    if (out / "boxes.json").exists():
        return out
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "color").mkdir(parents=True)
    for frame in sorted((large / "color").glob("*.png")):
        image = Image.open(frame)
        small = (image.resize((image.width // 2, image.height // 2), Image.BILINEAR)
                 if how == "resize" else Image.fromarray(np.asarray(image)[::2, ::2]))
        small.save(tmp / "color" / frame.name)
    shutil.copytree(large / "pose", tmp / "pose")
    (tmp / "intrinsic").mkdir()
    K = np.loadtxt(large / "intrinsic" / "intrinsic_color.txt")
    K[:2] /= 2
    if how == "resize":
        K[:2, 2] -= 0.25
    np.savetxt(tmp / "intrinsic" / "intrinsic_color.txt", K)
    shutil.copy(large / "intrinsic" / "extrinsic_color.txt", tmp / "intrinsic")
    for name in ("scene.json", "boxes.json"):
        shutil.copy(large / name, tmp / name)
    tmp.rename(out)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=str(common.ROOT / "models" / "parq-demo"),
                   help="model folder (default models/parq-demo), run at its card's setting")
    p.add_argument("--scenes", type=int, default=40,
                   help=f"held-out scenes (parq-synth seed {tradeoff.HELD_OUT_SEED}; default 40)")
    p.add_argument("--out", default=str(common.RESULTS / "resize_softness"),
                   help="output stem: .md and .json (default results/resize_softness)")
    args = p.parse_args()

    from parq_runtime import Detector

    native = tradeoff.held_out_scenes(args.scenes, 60, (160, 120))
    large = tradeoff.held_out_scenes(args.scenes, 60, (320, 240))
    sampled = [halved(f, common.CACHE / "held_out_320x240_pointsampled" / f.name, "point")
               for f in large]
    resized = [halved(f, common.CACHE / "held_out_320x240_resized" / f.name, "resize")
               for f in large]
    detector = Detector(args.model)
    model = pathlib.Path(args.model).resolve()
    model = model.relative_to(common.ROOT) if model.is_relative_to(common.ROOT) else model
    arms = (native, large, sampled, resized)
    truth = spread.truth_counts(native, detector.classes)
    if any(not np.array_equal(spread.truth_counts(s, detector.classes), truth)
           for s in arms[1:]):
        raise SystemExit("resize_softness: the renders hold different ground truth")
    iters, queries = detector.card.run_setting(None, None)
    counts = [spread.scene_counts(detector, scenes, iters, queries) for scenes in arms]
    rows = spread.spread(counts, 10000, 40)
    lines = [f"{model} at {iters} x {queries}"
             f"{', mirror runs' if detector.card.run_mirror else ''}, on {args.scenes} held-out "
             f"rooms (parq-synth seed {tradeoff.HELD_OUT_SEED}) rendered at two sizes; 90% "
             "intervals and paired differences from 10,000 resamples of the scenes.", "",
             "| frames | F1@0.25 | vs 160x120, paired | F1@0.5 | vs 160x120, paired |",
             "|---|---|---|---|---|"]
    for label, row in zip(LABELS, rows):
        lines.append("| " + " | ".join([label] + spread.paired_cells(row)) + " |")
    common.write_report(pathlib.Path(args.out), lines, {
        "model": str(model), "scenes": args.scenes, "seed": tradeoff.HELD_OUT_SEED,
        "setting": {"iters": iters, "queries": queries, "mirror": detector.card.run_mirror},
        "frames": list(LABELS), "rows": rows,
        "scene_counts": {label: c.tolist() for label, c in zip(LABELS, counts)}})


if __name__ == "__main__":
    main()
