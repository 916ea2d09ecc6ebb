"""Which objects the demo misses, and why: per class, by what is near them, by what they show.

parq-run's pipeline with the model card's run setting and post-processing, on the validation
scenes given (--val) or, without them, on the held-out scenes of tradeoff.py (seed 3000).
Each ground-truth box is found (a scene box of its class overlaps it at IoU 0.25, parq-eval's
matching) or missed, and a missed one is put in the first bin that fits:

* *same class near*: a scene box of its class has its centre within 0.5 m (horizontally): a
  localisation miss;
* *other class over it*: a scene box of another class overlaps it at IoU 0.25: a naming miss;
* *other class near*: a scene box of another class has its centre within 0.5 m;
* *nothing near*: no scene box of any class within 0.5 m: the network did not find it.

It also says whether each object is a training target in some snippet: the rule training uses,
``parq_train.data.snippet_targets`` (centre inside the decoder box, in view of some view and
not behind a nearer surface), on the training-style windows (every keyframe starts one), and
how many pixels the capture shows of it (parq-synth's ``visible`` record). Objects that are
never a target cannot be learned; the table says how many of them show enough to be found.

    python benchmarks/misses.py [--model models/parq-demo] [--val data/val] [--scenes 40]
"""
from __future__ import annotations

import argparse
import json
import pathlib
from collections import Counter

import numpy as np

import common
from tradeoff import add_scene_arguments, run_scenes, scenes_from_arguments

NEAR = 0.5          # metres, horizontal distance between centres
IOU = 0.25
PIXEL_BINS = (0, 1, 800, 3000)    # lower edges of PIXEL_BIN_NAMES
PIXEL_BIN_NAMES = ("not shown", "under 800 px", "800-3000 px", "3000 px or more")


def target_anywhere(folder: pathlib.Path, boxes: list, decoder_scale,
                    snippet_gap: int) -> np.ndarray:
    """(boxes,) bool: whether each of ``boxes`` (``folder``'s boxes.json) is a training target of
    some snippet (parq_train.data.snippet_targets on the windows training takes, stride 1)."""
    from parq_train import data
    from parq_runtime import keyframes
    from parq_runtime.readers import open_capture

    capture = open_capture(folder, "scannet")
    centers = np.array([b["center"] for b in boxes], np.float64).reshape(-1, 3)
    sizes = np.array([b["size"] for b in boxes], np.float64).reshape(-1, 3)
    keys = keyframes.select([f.cam_to_world for f in capture.frames])
    depths = {}                                   # keyframe index -> (depth, K), read once
    target = np.zeros(len(boxes), bool)
    for window in keyframes.windows(keys, 3, 1, snippet_gap):
        frames = [capture.frames[i] for i in window]
        for i, f in zip(window, frames):
            if i not in depths:
                depths[i] = (data.read_depth(folder, f.name), f.intrinsics)
        target |= data.snippet_targets(centers, sizes, np.stack([f.cam_to_world for f in frames]),
                                       [depths[i] for i in window], decoder_scale)[2]
    return target


def miss_reason(truth, fused: list, up) -> str:
    """The first bin (see the module docstring) a missed ground-truth box falls in."""
    from parq_runtime.iou import iou_matrix

    def nearest(boxes):
        if not boxes:
            return np.inf
        d = np.array([np.asarray(b.center, float) - np.asarray(truth.center, float)
                      for b in boxes])
        d -= np.outer(d @ np.asarray(up, float), np.asarray(up, float))
        return float(np.linalg.norm(d, axis=1).min())

    same = [b for b in fused if b.class_name == truth.class_name]
    other = [b for b in fused if b.class_name != truth.class_name]
    if nearest(same) < NEAR:
        return "same class near"
    if other and iou_matrix(other, [truth], up).max() > IOU:
        return "other class over it"
    if nearest(other) < NEAR:
        return "other class near"
    return "nothing near"


def pixel_bin(pixels: int) -> str:
    return PIXEL_BIN_NAMES[int(np.searchsorted(PIXEL_BINS, pixels, side="right")) - 1]


def analyse(detector, scenes: list) -> list:
    """One record per ground-truth box: class, found, why missed, target, pixels shown."""
    from parq_runtime import evaluation

    from parq_train.data import read_boxes

    card = detector.card
    pairs, _ = run_scenes(detector, scenes, None, None)
    rows = []
    for folder, (fused, truth, up) in zip(scenes, pairs):
        _, found = evaluation.matches(fused, truth, IOU, up)
        boxes = read_boxes(folder / "boxes.json")
        target = target_anywhere(folder, boxes, card.decoder_scale, card.snippet_gap)
        for j, box in enumerate(truth):
            rows.append({"scene": folder.name, "class": box.class_name,
                         "found": bool(found[j]),
                         "why": None if found[j] else miss_reason(box, fused, up),
                         "target": bool(target[j]),
                         "pixels": int(boxes[j].get("visible", {}).get("max_pixels", -1))})
    return rows


def report(rows: list, what: str) -> list:
    n = len(rows)
    found = sum(r["found"] for r in rows)
    lines = [f"# Misses of the card at its run setting: {what}", "",
             f"{found} of {n} objects found at IoU {IOU} (recall {found / n:.3f}).", "",
             "| class | objects | found | share found | a training target | found of targets |",
             "|---|---:|---:|---:|---:|---:|"]
    counts = Counter(r["class"] for r in rows)
    classes = sorted(counts, key=lambda c: (-counts[c], c))      # ties by name: a stable table
    for c in classes:
        mine = [r for r in rows if r["class"] == c]
        t = [r for r in mine if r["target"]]
        f = sum(r["found"] for r in mine)
        lines.append(f"| {c} | {len(mine)} | {f} | {f / len(mine):.2f} | {len(t)} | "
                     f"{sum(r['found'] for r in t) / max(1, len(t)):.2f} |")
    why = Counter(r["why"] for r in rows if not r["found"])
    lines += ["", "| missed objects, by what is near them | objects |", "|---|---:|"]
    lines += [f"| {k} | {v} |" for k, v in why.most_common()]
    lines += ["", "| pixels shown (most in one frame) | objects | a training target | found |",
              "|---|---:|---:|---:|"]
    for name in PIXEL_BIN_NAMES:
        mine = [r for r in rows if pixel_bin(r["pixels"]) == name]
        lines.append(f"| {name} | {len(mine)} | {sum(r['target'] for r in mine)} | "
                     f"{sum(r['found'] for r in mine)} |")
    never = [r for r in rows if not r["target"]]
    lines += ["", f"Never a training target: {len(never)} objects, of which "
              f"{sum(r['pixels'] >= 1000 for r in never)} show 1,000 pixels or more in some "
              f"frame and {sum(r['found'] for r in never)} are found."]
    return lines


def shown(path) -> str:
    """``path`` relative to the repository when it lies inside it (the report's command then
    runs from any checkout), else as given."""
    path = pathlib.Path(path).resolve()
    return str(path.relative_to(common.ROOT)) if path.is_relative_to(common.ROOT) else str(path)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scene_arguments(p, "analyse")
    p.add_argument("--val", type=pathlib.Path, nargs="+", default=None,
                   help="validation folders of scenes to analyse instead of the held-out ones")
    p.add_argument("--out", default=str(common.RESULTS / "misses"),
                   help="output stem: .md and .json (default results/misses)")
    args = p.parse_args()
    from parq_runtime import Detector

    detector = Detector(args.model)
    if args.val:
        scenes = [f for folder in args.val for f in sorted(folder.glob("scene_*"))][:args.scenes]
        what = f"{len(scenes)} scenes of {', '.join(map(str, args.val))}"
    else:
        scenes, _ = scenes_from_arguments(args)
        what = f"{len(scenes)} held-out scenes (seed 3000)"
    rows = analyse(detector, scenes)
    model = shown(args.model)
    lines = report(rows, f"{what}, {model}")
    lines += ["", f"    python benchmarks/misses.py --model {model} --scenes {args.scenes}"
              + (f" --val {' '.join(map(str, args.val))}" if args.val else "")]
    out = pathlib.Path(args.out)
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"model": model, "what": what,
                                                    "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
