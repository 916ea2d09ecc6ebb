"""parq-eval: scene-level precision, recall and F1 at 3D IoU 0.25, 0.5 and 0.7.

The authors' protocol (ODAM's, ``utils/f1_eval.py``): the scene's fused predictions are compared
with its ground-truth boxes; a prediction is a true positive when it has the ground truth's
class and their upright 3D IoU is above the threshold, and each ground-truth box is matched at
most once.  Precision = TP / predictions, recall = TP / ground-truth boxes, F1 their harmonic
mean, per class and over all classes pooled (micro average).

Three deliberate differences from their code, each documented in the README:

* one prediction matches at most one ground-truth box.  Their loop goes on after a match, so
  one prediction overlapping two boxes of its class counted two true positives;
* within a class, predictions are matched in decreasing score, each to the unmatched box it
  overlaps most (theirs: prediction list order, first box above the threshold).
* the pooled average counts every class.  Theirs skips classes with no prediction at all, so
  the ground truth of a class the model never predicts did not lower recall.

``--seen-only`` scores against the boxes some frame of the capture shows.  ScanNet's boxes come
from the reconstructed scan, so an object its camera never saw has none; parq-synth's
boxes.json lists every object in the room, and records per box how much of it the capture shows
(``"visible": {"frames", "max_pixels"}``, from the rendered instance masks).  The option drops
boxes with ``frames == 0`` before matching; a prediction on such an object is then a false
positive, as it would be against ScanNet's boxes.  The default counts every box.
"""
from __future__ import annotations

import json
import pathlib
import reprlib
import sys

import numpy as np

from . import files, geometry
from .boxes import Box
from .errors import ParqError
from .files import read_json
from .iou import iou_matrix
from .results import SCHEMA, VERSION

THRESHOLDS = (0.25, 0.5, 0.7)
BOXES_FORMAT = "parq-onnx-boxes"
# |R^T R - I| a box's rotation may have (files round their numbers)
ROTATION_TOL = 1e-3


def load_ground_truth(path, seen_only: bool = False) -> tuple:
    """(boxes, up) from a boxes.json written by parq-synth (or by hand, same schema);
    ``seen_only``: only the boxes whose "visible" record says some frame shows them."""
    path = pathlib.Path(path)
    data = _read_json(path)
    if not isinstance(data, dict) or data.get("format") != BOXES_FORMAT:
        raise ParqError(f"{path}: not a ground-truth boxes.json (format {BOXES_FORMAT!r})")
    records = data.get("boxes")
    if not isinstance(records, list):
        raise ParqError(f'{path}: no "boxes" list')
    up = _floats(data.get("up", geometry.UP_Z), (3,))
    if up is None or not 0 < np.linalg.norm(up) < np.inf:
        raise ParqError(f'{path}: "up" must be three finite numbers, not all zero, got '
                        f"{reprlib.repr(data['up'])}")
    where = [f"{path}: box {i}" for i in range(len(records))]
    boxes = [_box(b, w) for b, w in zip(records, where)]
    if seen_only:
        boxes = [b for b, r, w in zip(boxes, records, where) if _shown(r, w)]
    return boxes, tuple(float(v) for v in up)


def load_predictions(path) -> list:
    """The scene boxes of a parq-run output JSON, as :class:`Box` objects."""
    data = _read_json(path)
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise ParqError(f"{path}: not a parq-run output (schema {SCHEMA!r} expected)")
    if data.get("version") != VERSION:
        raise ParqError(f"{path}: parq-run output version {data.get('version')}, expected "
                        f"{VERSION}")
    if not isinstance(data.get("scene"), dict):
        raise ParqError(f'{path}: not a parq-run output (no "scene" section)')
    records = data["scene"].get("boxes")
    if not isinstance(records, list):
        raise ParqError(f'{path}: "scene" has no "boxes" list')
    return [_box(b, f"{path}: scene box {i}") for i, b in enumerate(records)]


def _read_json(path):
    """files.read_json, with a file nested too deeply for the parser refused as well."""
    try:
        return read_json(path)
    except RecursionError:
        raise ParqError(f"{path}: not readable JSON (nested too deeply)") from None


def _box(record, where: str) -> Box:
    """A :class:`Box` from one box record (parq-run's box or boxes.json's), checked first:
    ParqError starting with ``where`` when a value is missing or not what the schema says."""
    if not isinstance(record, dict):
        raise ParqError(f"{where}: not a JSON object, got {reprlib.repr(record)}")
    for key in ("label", "center", "size", "rotation"):
        if key not in record:
            raise ParqError(f'{where}: missing "{key}"')

    def refuse(key, what):
        raise ParqError(f"{where}: {key} must be {what}, got {reprlib.repr(record[key])}")

    label = record["label"]
    if isinstance(label, bool) or not isinstance(label, int) or label < 0:
        refuse("label", "a class index (an integer, 0 or more)")
    if not isinstance(record.get("class", ""), str):
        refuse("class", "a class name (a string)")
    center = _floats(record["center"], (3,))
    if center is None:
        refuse("center", "three finite numbers")
    size = _floats(record["size"], (3,))
    if size is None or size.min() <= 0:
        refuse("size", "three positive finite numbers")
    for key, v in (("center", center), ("size", size)):
        if np.abs(v).max() > geometry.MAX_TRANSLATION:
            raise ParqError(f"{where}: {key} {reprlib.repr(record[key])} is beyond "
                            f"{geometry.MAX_TRANSLATION:.0e} m (wrong units?)")
    R = _floats(record["rotation"], (3, 3))
    if R is None or np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOL or np.linalg.det(R) < 0:
        refuse("rotation", "a 3x3 rotation matrix (orthonormal, determinant +1)")
    for key in ("score", "yaw"):
        if key in record and _floats(record[key], ()) is None:
            refuse(key, "a finite number")
    return Box.from_json(record)


def _floats(value, shape: tuple):
    """``value`` as a float64 array of ``shape`` when it is numbers (not booleans) nested in
    lists of that shape, all finite; None otherwise."""
    def numbers(v, shape):
        if not shape:
            return isinstance(v, (int, float)) and not isinstance(v, bool)
        return (isinstance(v, (list, tuple)) and len(v) == shape[0]
                and all(numbers(x, shape[1:]) for x in v))
    if not numbers(value, shape):
        return None
    try:
        a = np.asarray(value, dtype=np.float64)
    except OverflowError:   # an integer beyond the float range
        return None
    return a if np.all(np.isfinite(a)) else None


def _shown(record, where: str) -> bool:
    """Whether a box record's "visible" entry says some frame shows it."""
    visible = record.get("visible")
    frames = visible.get("frames") if isinstance(visible, dict) else None
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
        raise ParqError(f"{where}: no valid \"visible\": {{\"frames\": N}} record, "
                        "which --seen-only needs (parq-synth writes one per box; scenes it "
                        "generated before that have none: generate the scene again)")
    return frames > 0


def match_counts(predictions: list, truth: list, threshold: float, classes: list,
                 up=geometry.UP_Z) -> dict:
    """Per-class {"tp", "predictions", "ground_truth"} for one scene."""
    hit, _ = matches(predictions, truth, threshold, up)
    counts = {c: {"tp": 0, "predictions": 0, "ground_truth": 0} for c in classes}
    for p, found in zip(predictions, hit):
        if p.class_name in counts:
            counts[p.class_name]["predictions"] += 1
            counts[p.class_name]["tp"] += int(found)
    for g in truth:
        if g.class_name in counts:
            counts[g.class_name]["ground_truth"] += 1
    return counts


def matches(predictions: list, truth: list, threshold: float, up=geometry.UP_Z) -> tuple:
    """(predictions (P,) bool: a true positive, truth (G,) bool: found) for one scene, in the
    lists' order: within each class, predictions in decreasing score each take the unmatched
    ground-truth box of their class they overlap most, if above ``threshold``."""
    hit = np.zeros(len(predictions), dtype=bool)
    found = np.zeros(len(truth), dtype=bool)
    for name in {p.class_name for p in predictions}:
        mine = sorted((i for i, p in enumerate(predictions) if p.class_name == name),
                      key=lambda i: -predictions[i].score)
        theirs = [j for j, g in enumerate(truth) if g.class_name == name]
        if not theirs:
            continue
        iou = iou_matrix([predictions[i] for i in mine], [truth[j] for j in theirs], up)
        for row, i in enumerate(mine):
            candidates = np.where(~found[theirs] & (iou[row] > threshold), iou[row], -1.0)
            col = int(np.argmax(candidates))
            if candidates[col] > 0:
                found[theirs[col]] = True
                hit[i] = True
    return hit, found


def classes_of(*box_lists) -> list:
    """Class names present, in label order."""
    labels = {}
    for boxes in box_lists:
        for b in boxes:
            labels.setdefault(b.class_name, b.label)
    return sorted(labels, key=lambda name: (labels[name], name))


def _prf(tp, n_pred, n_gt) -> dict:
    precision = tp / n_pred if n_pred else 0.0
    recall = tp / n_gt if n_gt else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp,
            "predictions": n_pred, "ground_truth": n_gt}


def evaluate(scenes: list, classes=None, thresholds=THRESHOLDS) -> dict:
    """scenes: [(predicted boxes, ground-truth boxes, up), ...]; counts are pooled over
    scenes.  Returns {"0.25": {"precision", "recall", "f1", "per_class": {...}}, ...}."""
    if classes is None:
        classes = classes_of(*[preds + gts for preds, gts, _ in scenes])
    out = {}
    for t in thresholds:
        total = {c: {"tp": 0, "predictions": 0, "ground_truth": 0} for c in classes}
        for preds, gts, up in scenes:
            for c, n in match_counts(preds, gts, t, classes, up).items():
                for k in n:
                    total[c][k] += n[k]
        pooled = [sum(total[c][k] for c in classes)
                  for k in ("tp", "predictions", "ground_truth")]
        out[str(t)] = dict(_prf(*pooled),
                           per_class={c: _prf(total[c]["tp"], total[c]["predictions"],
                                              total[c]["ground_truth"]) for c in classes})
    return out


def format_table(metrics: dict) -> str:
    lines = [f"{'IoU':>5}  {'precision':>9}  {'recall':>6}  {'F1':>6}"]
    for t, m in metrics.items():
        lines.append(f"{t:>5}  {m['precision']:9.3f}  {m['recall']:6.3f}  {m['f1']:6.3f}")
    classes = list(next(iter(metrics.values()))["per_class"])
    lines.append("")
    lines.append(f"{'class':12s} " + "  ".join(f"F1@{t:<5}" for t in metrics) + "  gt")
    for c in classes:
        row = [metrics[t]["per_class"][c]["f1"] for t in metrics]
        gt = next(iter(metrics.values()))["per_class"][c]["ground_truth"]
        lines.append(f"{c:12s} " + "  ".join(f"{v:8.3f}" for v in row) + f"  {gt}")
    return "\n".join(lines)


def main(argv=None) -> int:
    from .arguments import OneLineParser

    p = OneLineParser(
        prog="parq-eval",
        description="Scene-level precision / recall / F1 of parq-run's fused boxes against "
                    "ground truth, at 3D IoU 0.25, 0.5 and 0.7 (the authors' protocol, with "
                    "one prediction matching at most one box).")
    p.add_argument("predictions", type=pathlib.Path, help="parq-run output JSON")
    p.add_argument("ground_truth", type=pathlib.Path, help="boxes.json of the scene")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")
    p.add_argument("--seen-only", action="store_true",
                   help="score only the ground-truth boxes that some frame of the capture "
                        "shows (boxes.json's per-box \"visible\" record, written by "
                        "parq-synth), as ScanNet's ground truth holds only what its scan saw")
    args = p.parse_args(argv)
    try:
        truth, up = load_ground_truth(args.ground_truth, seen_only=args.seen_only)
        predictions = load_predictions(args.predictions)
        metrics = evaluate([(predictions, truth, up)], classes_of(predictions, truth))
    except ParqError as e:
        print(f"parq-eval: error: {e}", file=sys.stderr)
        return e.exit_code
    files.write_stdout(json.dumps(metrics, indent=1) if args.json else format_table(metrics))
    return 0


if __name__ == "__main__":
    sys.exit(main())
