"""IoU, scene fusion and the F1 evaluator on hand-made cases with known answers."""
import dataclasses
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from parq_runtime import geometry
from parq_runtime.boxes import Box
from parq_runtime.evaluation import evaluate, match_counts, matches
from parq_runtime.fusion import SceneFusion
from parq_runtime.iou import footprint, iou_matrix, iou_upright, vertical_range

Y_UP = (0.0, 1.0, 0.0)


def box(center, size=(1, 1, 1), yaw=0.0, name="chair", score=0.9, up=geometry.UP_Z):
    e1, e2 = geometry.horizontal_basis(up)
    x = np.cos(yaw) * e1 + np.sin(yaw) * e2
    y = np.asarray(up, dtype=float)
    R = np.stack([x, y, np.cross(x, y)], -1)
    labels = {"chair": 0, "table": 1}
    return Box(np.asarray(center, float), np.asarray(size, float), R, yaw, labels[name], name,
               score, geometry.box_corners(np.asarray(center, float), np.asarray(size, float), R))


def test_iou_matrix_is_the_pairwise_iou_whatever_the_company():
    """iou_matrix screens pairs (height overlap, footprint distance) for many boxes at once:
    each entry must be what the polygon intersection of the pair gives without screening,
    including pairs that are far apart or sit one on the other, and the matrix must be
    symmetric with ones on its diagonal."""
    rng = np.random.default_rng(0)
    boxes = [box(rng.uniform(-2, 2, 3), size=rng.uniform(0.2, 1.5, 3),
                 yaw=rng.uniform(-np.pi, np.pi)) for _ in range(25)]
    boxes.append(box(boxes[0].center + [0, 0, boxes[0].size[1]], size=boxes[0].size))  # on top
    m = iou_matrix(boxes, boxes)

    def brute_force(a, b):   # every pair through the polygon intersection, no screening
        (lo_a, hi_a), (lo_b, hi_b) = vertical_range(a.center, a.size), \
            vertical_range(b.center, b.size)
        area, _ = cv2.intersectConvexConvex(
            footprint(a.center, a.size, a.yaw).astype(np.float32),
            footprint(b.center, b.size, b.yaw).astype(np.float32))
        inter = max(area, 0.0) * max(min(hi_a, hi_b) - max(lo_a, lo_b), 0.0)
        return inter / (np.prod(a.size) + np.prod(b.size) - inter)

    np.testing.assert_allclose(m, [[brute_force(a, b) for b in boxes] for a in boxes],
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(m, m.T, atol=1e-6)
    np.testing.assert_allclose(np.diag(m), 1.0, atol=1e-6)
    assert m[0, -1] == 0.0 and 0 < (m > 0).sum() - len(boxes) < len(boxes) ** 2 - len(boxes)
    assert iou_matrix([], boxes).shape == (0, len(boxes))
    assert iou_matrix(boxes, []).shape == (len(boxes), 0)


@pytest.mark.parametrize("up", [geometry.UP_Z, Y_UP])
def test_iou_known_values(up):
    up_v = np.asarray(up)
    e1, e2 = geometry.horizontal_basis(up)
    a = box([0, 0, 0], up=up)
    assert iou_upright(a, box([0, 0, 0], up=up), up) == pytest.approx(1.0)
    # half a box along a horizontal axis: overlap 1/2, union 3/2
    assert iou_upright(a, box(0.5 * e1, up=up), up) == pytest.approx(1 / 3)
    # half a box up: same
    assert iou_upright(a, box(0.5 * up_v, up=up), up) == pytest.approx(1 / 3)
    # 45 degrees about up: the footprints intersect in a regular octagon of area 2(sqrt2 - 1)
    octagon = 2 * (np.sqrt(2) - 1)
    assert iou_upright(a, box([0, 0, 0], yaw=np.pi / 4, up=up), up) == \
        pytest.approx(octagon / (2 - octagon), rel=1e-5)
    # a 2x1x1 box turned 90 degrees over another: footprint overlap 1, height 1, union 3
    long_a = box([0, 0, 0], size=(2, 1, 1), up=up)
    long_b = box([0, 0, 0], size=(2, 1, 1), yaw=np.pi / 2, up=up)
    assert iou_upright(long_a, long_b, up) == pytest.approx(1 / 3, rel=1e-5)
    assert iou_upright(a, box(2 * e2, up=up), up) == 0.0
    assert iou_upright(a, box(1.5 * up_v, up=up), up) == 0.0


def test_matching_counts_and_one_prediction_per_box():
    gts = [box([0, 0, 0.5]), box([3, 0, 0.5])]
    preds = [box([0, 0, 0.5], score=0.95),                  # exact: TP
             box([0.05, 0, 0.5], score=0.9),                 # duplicate of the same box: FP
             box([3.4, 0, 0.5], score=0.8)]                  # IoU 0.6/1.4 = 0.43
    c = match_counts(preds, gts, 0.25, ["chair"])["chair"]
    assert c == {"tp": 2, "predictions": 3, "ground_truth": 2}
    c = match_counts(preds, gts, 0.5, ["chair"])["chair"]
    assert c["tp"] == 1
    # one big prediction over two small boxes of its class counts once (the authors' loop
    # counted it twice)
    small = [box([-0.25, 0, 0.5], size=(0.5, 1, 1)), box([0.25, 0, 0.5], size=(0.5, 1, 1))]
    big = [box([0, 0, 0.5], size=(1, 1, 1))]
    assert match_counts(big, small, 0.25, ["chair"])["chair"]["tp"] == 1
    # the class must agree
    assert match_counts([box([0, 0, 0.5], name="table")], gts, 0.25,
                        ["chair", "table"])["table"]["tp"] == 0
    # which ones: the better-scoring of two on one box takes it, whatever the list order
    hit, found = matches(preds[::-1], gts + [box([9, 0, 0.5], name="table")], 0.25)
    assert hit.tolist() == [True, False, True] and found.tolist() == [True, True, False]


def test_precision_recall_f1_pooled_over_scenes_and_classes():
    scene1 = ([box([0, 0, 0.5]), box([5, 5, 0.5], name="table")],       # 1 TP, 1 FP
              [box([0, 0, 0.5]), box([2, 0, 0.5])], geometry.UP_Z)      # 2 chairs
    scene2 = ([box([1, 1, 0.5], name="table")],                         # 1 TP
              [box([1, 1, 0.5], name="table"), box([9, 9, 0.5], name="table")], geometry.UP_Z)
    m = evaluate([scene1, scene2], ["chair", "table"])
    for t in ("0.25", "0.5", "0.7"):
        # TP 2, predictions 3, ground truth 4
        assert m[t]["precision"] == pytest.approx(2 / 3)
        assert m[t]["recall"] == pytest.approx(2 / 4)
        assert m[t]["f1"] == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
        assert m[t]["per_class"]["chair"]["recall"] == pytest.approx(0.5)
        assert m[t]["per_class"]["table"]["precision"] == pytest.approx(0.5)


def test_scene_fusion_replaces_by_score_and_adds_unmatched():
    fusion = SceneFusion()
    fusion.add([box([0, 0, 0.5], score=0.85), box([3, 0, 0.5], score=0.9)], 0)
    # overlaps the first (IoU 0.82): replaces it (higher score); a far one is added; one
    # overlapping the second with a lower score leaves it alone
    fusion.add([box([0.1, 0, 0.5], score=0.95), box([8, 0, 0.5], score=0.99),
                box([3.05, 0, 0.5], score=0.5)], 1)
    assert len(fusion.boxes) == 3
    assert fusion.boxes[0].score == 0.95 and fusion.sources[0] == 1
    assert fusion.boxes[1].score == 0.9 and fusion.sources[1] == 0
    # IoU under 0.1 does not match: 0.95 of a box away
    fusion.add([box([1.05, 0.0, 0.5], score=0.99)], 2)
    assert len(fusion.boxes) == 4


def test_mean_fusion_averages_the_best_class_weighted_by_score():
    fusion = SceneFusion(mode="mean")
    fusion.add([box([0.0, 0, 0.5], size=(1, 1, 1), score=0.6)], 0)
    fusion.add([box([0.2, 0, 0.5], size=(1.2, 1, 1), score=0.9)], 1)
    # another class in the same cluster: matched, but not averaged into the chair
    fusion.add([box([0.1, 0, 0.5], name="table", score=0.3)], 2)
    (fused,) = fusion.boxes
    np.testing.assert_allclose(fused.center, [(0.6 * 0.0 + 0.9 * 0.2) / 1.5, 0, 0.5])
    np.testing.assert_allclose(fused.size, [(0.6 * 1.0 + 0.9 * 1.2) / 1.5, 1, 1])
    assert fused.class_name == "chair" and fused.score == 0.9 and fusion.sources == [1]
    np.testing.assert_allclose(fused.corners, geometry.box_corners(fused.center, fused.size,
                                                                   fused.rotation))
    # the authors' mode keeps the best detection as it is
    best = SceneFusion(mode="best")
    best.add([box([0.0, 0, 0.5], score=0.6)], 0)
    best.add([box([0.2, 0, 0.5], score=0.9)], 1)
    np.testing.assert_allclose(best.boxes[0].center, [0.2, 0, 0.5])


def test_mean_fusion_averages_sizes_in_the_best_detections_axes():
    """A table 2 m long and 1 m deep, detected once as it is and once turned by 90 degrees with
    its extents swapped (the same box): the fused box is the table, not a 1.5 m square."""
    table = dict(name="table", up=geometry.UP_Z)
    for mode in ("mean", "ray"):
        fusion = SceneFusion(mode=mode)
        fusion.add([box([0, 0, 0.4], size=(2.0, 0.8, 1.0), yaw=0.0, score=0.9, **table)], 0)
        fusion.add([box([0, 0, 0.4], size=(1.0, 0.8, 2.0), yaw=np.pi / 2 + 0.1, score=0.9,
                        **table)], 1)
        fusion.add([box([0, 0, 0.4], size=(2.2, 0.8, 1.2), yaw=np.pi - 0.2, score=0.9,
                        **table)], 2)
        (fused,) = fusion.boxes
        np.testing.assert_allclose(fused.size, [(2.0 + 2.0 + 2.2) / 3, 0.8, (1 + 1 + 1.2) / 3])
        truth = box([0, 0, 0.4], size=(2.0, 0.8, 1.0), **table)
        assert iou_matrix([fused], [truth], geometry.UP_Z)[0, 0] > 0.9


def seen_from(b, viewpoint):
    return dataclasses.replace(b, viewpoint=np.asarray(viewpoint, float))


def test_ray_fusion_pins_the_depth_that_each_view_gets_wrong():
    """An object at (2, 2, 0.5) seen along +x from (0, 2, 0.5) and along +y from (2, 0, 0.5),
    each detection 0.3 m too deep along its own ray.  The mean is 0.21 m off; ray fusion with
    ratio k solves ((I - 0.9 xx^T) + (I - 0.9 yy^T)) c = ..., i.e. x = (2.3 / k + 2) / (1 + 1/k)
    and y = (2 + 1.7 / k) / (1 + 1/k): 0.039 m off at k = 10, exact as k grows."""
    truth = np.array([2.0, 2.0, 0.5])
    a = seen_from(box(truth + [0.3, 0, 0], score=0.9), [0, 2, 0.5])
    b = seen_from(box(truth - [0, 0.3, 0], score=0.9), [2, 0, 0.5])
    errors = {}
    for mode, ratio in (("mean", 10.0), ("ray", 1.0), ("ray", 10.0), ("ray", 1e6)):
        fusion = SceneFusion(mode=mode, ray_ratio=ratio)
        fusion.add([a], 0)
        fusion.add([b], 1)
        (fused,) = fusion.boxes
        errors[mode, ratio] = np.linalg.norm(fused.center - truth)
        np.testing.assert_allclose(fused.corners, geometry.box_corners(
            fused.center, fused.size, fused.rotation))
    k = 10.0
    expected = [(2.3 / k + 2) / (1 + 1 / k), (2 + 1.7 / k) / (1 + 1 / k), 0.5]
    fusion = SceneFusion(mode="ray", ray_ratio=k)
    fusion.add([a], 0)
    fusion.add([b], 1)
    np.testing.assert_allclose(fusion.boxes[0].center, expected, atol=1e-12)
    assert errors["mean", 10.0] == pytest.approx(0.3 / np.sqrt(2))
    assert errors["ray", 1.0] == pytest.approx(errors["mean", 10.0])    # ratio 1 is the mean
    assert errors["ray", 10.0] < 0.04 and errors["ray", 1e6] < 1e-5


def test_ray_fusion_without_viewpoints_is_the_mean_and_bad_ratios_are_refused():
    from parq_runtime.errors import ParqError

    fused = {}
    for mode in ("mean", "ray"):
        fusion = SceneFusion(mode=mode)
        fusion.add([box([0.0, 0, 0.5], score=0.6)], 0)            # no viewpoint: isotropic
        fusion.add([box([0.2, 0.1, 0.5], score=0.9)], 1)
        fused[mode] = fusion.boxes[0].center
    np.testing.assert_allclose(fused["ray"], fused["mean"], atol=1e-12)
    for ratio in (0.5, float("inf"), float("nan"), "10", True):
        with pytest.raises(ParqError, match="ray_ratio"):
            SceneFusion(mode="ray", ray_ratio=ratio)


def test_min_support_counts_snippets_not_detections():
    fusion = SceneFusion(min_support=2)
    fusion.add([box([0, 0, 0.5]), box([5, 0, 0.5])], 0)
    assert fusion.boxes == []
    fusion.add([box([0.05, 0, 0.5])], 1)           # the first box, seen again
    fusion.add([box([9, 0, 0.5])], 1)              # a new box, once
    assert [round(float(b.center[0]), 2) for b in fusion.boxes] == [0.0]
    assert fusion.supports == [2] and fusion.sources == [0]
    assert SceneFusion(min_support=1).min_support == 1
    from parq_runtime.errors import ParqError
    with pytest.raises(ParqError, match="fusion mode"):
        SceneFusion(mode="median")
    with pytest.raises(ParqError, match="min_support"):
        SceneFusion(min_support=0)


def test_support_counts_each_run_of_a_snippet_once_mirror_and_sampling_grid_apart():
    """One snippet's four runs (plain and mirrored, at two point-sampling grids) that all see
    a box give it support 4; a run that sees it twice still counts once."""
    fusion = SceneFusion(min_support=4)
    for mirrored in (False, True):
        for phase in (0.0, 0.5):
            assert fusion.boxes == []                      # support 1 to 3 of 4
            fusion.add([box([0.01, 0, 0.5])], 0, mirrored, phase)
    fusion.add([box([0.02, 0, 0.5])], 0, True, 0.5)
    assert fusion.supports == [4] and fusion.sources == [0]


def test_scene_nms_keeps_one_box_per_object_and_class():
    """Two clusters grown on one chair (a snippet's two detections each start one) are one
    object under scene NMS: the better-scoring stays, sources and supports follow it; a table
    in the same place is another object; off (None) reports both, as before."""
    from parq_runtime.errors import ParqError

    def fused(scene_nms):
        fusion = SceneFusion(scene_nms=scene_nms)
        fusion.add([box([0, 0, 0.5], score=0.8), box([0.6, 0, 0.5], score=0.9),
                    box([0.3, 0, 0.5], name="table", score=0.7), box([4, 0, 0.5])], 0)
        fusion.add([box([0.62, 0, 0.5], score=0.6)], 1)
        return fusion

    assert len(fused(None).boxes) == 4
    fusion = fused(0.05)                     # the chairs' IoU: 0.4 / 1.6 = 0.25
    assert [(b.class_name, round(float(b.center[0]), 1)) for b in fusion.boxes] == [
        ("chair", 0.6), ("table", 0.3), ("chair", 4.0)]
    assert fusion.supports == [2, 1, 1] and fusion.sources == [0, 0, 0]
    assert len(fused(0.3).boxes) == 4        # overlapping less than the threshold: both kept
    assert len(fusion.boxes_with_support(2)) == 1
    for bad in (1.0, -0.1, True, "0.1"):
        with pytest.raises(ParqError, match="scene_nms"):
            SceneFusion(scene_nms=bad)


def test_matching_iou_joins_barely_overlapping_detections_of_one_object():
    """Two snippets' detections of one 1 m box, 0.85 m apart along its depth (IoU 0.15 / 1.85
    = 0.08): under the authors' matching IoU of 0.1 they grow two scene boxes of support 1,
    which a support of 2 drops; at 0.05 they are one box of support 2 between them."""
    from parq_runtime.errors import ParqError

    def fused(*match_iou):
        fusion = SceneFusion(*match_iou, mode="mean")
        fusion.add([box([0.0, 0, 0.5], score=0.9)], 0)
        fusion.add([box([0.85, 0, 0.5], score=0.9)], 1)
        return fusion

    authors = fused()
    assert authors.supports == [1, 1] and authors.boxes_with_support(2) == []
    joined = fused(0.05)
    assert joined.supports == [2]
    assert np.allclose(joined.boxes_with_support(2)[0].center, [0.425, 0, 0.5])
    for bad in (0.0, 1.5, True, "0.1", float("nan")):
        with pytest.raises(ParqError, match="match_iou"):
            SceneFusion(bad)


def test_label_vote_takes_the_class_the_cluster_calls_it_most():
    """One object, detected by four snippets: three call it a table (0.7, 0.75, 0.8), one a
    chair (0.95).  ``best`` reports the chair; ``vote`` the table (scores 2.25 against 0.95),
    as the best table detection (0.8, snippet 3), averaged over the tables only; a tie in the
    sums goes to the class with the single best score."""
    from parq_runtime.errors import ParqError

    calls = [("table", 0.7, 0.0), ("chair", 0.95, 0.3), ("table", 0.75, 0.1),
             ("table", 0.8, 0.2)]
    fused = {}
    for labels in ("best", "vote"):
        fusion = SceneFusion(mode="mean", labels=labels)
        for n, (name, score, x) in enumerate(calls):
            fusion.add([box([x, 0, 0.5], name=name, score=score)], n)
        ((b,), sources, supports) = fusion.boxes, fusion.sources, fusion.supports
        fused[labels] = (b.class_name, b.score, float(b.center[0]), sources, supports)
    assert fused["best"] == ("chair", 0.95, 0.3, [1], [4])
    expected_x = (0.7 * 0.0 + 0.75 * 0.1 + 0.8 * 0.2) / 2.25
    assert fused["vote"][:2] == ("table", 0.8) and fused["vote"][3:] == ([3], [4])
    assert fused["vote"][2] == pytest.approx(expected_x)
    # the authors' mode reports the voted class's best detection as it is
    fusion = SceneFusion(labels="vote")
    for n, (name, score, x) in enumerate(calls):
        fusion.add([box([x, 0, 0.5], name=name, score=score)], n)
    assert (fusion.boxes[0].class_name, float(fusion.boxes[0].center[0])) == ("table", 0.2)
    # equal sums (0.5 each, exact in binary): the class with the best single detection
    tie = SceneFusion(labels="vote")
    tie.add([box([0, 0, 0.5], name="table", score=0.25)], 0)
    tie.add([box([0, 0, 0.5], name="chair", score=0.5)], 1)
    tie.add([box([0, 0, 0.5], name="table", score=0.25)], 2)
    assert tie.boxes[0].class_name == "chair"
    for bad in ("majority", None, 1):
        with pytest.raises(ParqError, match="fusion labels"):
            SceneFusion(labels=bad)


def test_parq_eval_cli(tmp_path):
    gt = {"format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1],
          "boxes": [box([0, 0, 0.5]).to_json(), box([2, 0, 0.5]).to_json()]}
    (tmp_path / "boxes.json").write_text(json.dumps(gt))
    pred = {"schema": "parq-onnx/detections", "version": 1,
            "scene": {"boxes": [box([0, 0, 0.5]).to_json()]}}
    (tmp_path / "pred.json").write_text(json.dumps(pred))
    p = subprocess.run([sys.executable, "-m", "parq_runtime.evaluation", tmp_path / "pred.json",
                        tmp_path / "boxes.json", "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    m = json.loads(p.stdout)
    assert set(m) == {"0.25", "0.5", "0.7"}
    assert m["0.5"]["precision"] == 1.0 and m["0.5"]["recall"] == 0.5
    assert set(m["0.5"]) == {"precision", "recall", "f1", "per_class", "tp", "predictions",
                             "ground_truth"}
    p = subprocess.run([sys.executable, "-m", "parq_runtime.evaluation", tmp_path / "nope.json",
                        tmp_path / "boxes.json"], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "nope.json" in p.stderr
    # a reader that stops early (| head) closes the pipe: no traceback.  stdout is closed
    # before the interpreter has started, so the write always meets the closed pipe.
    p = subprocess.Popen([sys.executable, "-m", "parq_runtime.evaluation",
                          tmp_path / "pred.json", tmp_path / "boxes.json", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    p.stdout.close()
    stderr = p.stderr.read()
    p.wait()
    p.stderr.close()
    assert "Traceback" not in stderr and "Error" not in stderr, stderr


def test_parq_eval_seen_only_drops_the_boxes_no_frame_shows(tmp_path):
    seen, unseen = box([0, 0, 0.5]).to_json(), box([3, 0, 0.5]).to_json()
    seen["visible"] = {"frames": 4, "max_pixels": 900}
    unseen["visible"] = {"frames": 0, "max_pixels": 0}
    gt = {"format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1],
          "boxes": [seen, unseen]}
    (tmp_path / "boxes.json").write_text(json.dumps(gt))
    pred = {"schema": "parq-onnx/detections", "version": 1,
            "scene": {"boxes": [box([0, 0, 0.5]).to_json(), box([3, 0.05, 0.5]).to_json(),
                                box([6, 0, 0.5]).to_json()]}}
    (tmp_path / "pred.json").write_text(json.dumps(pred))

    def scores(*flags):
        p = subprocess.run([sys.executable, "-m", "parq_runtime.evaluation",
                            tmp_path / "pred.json", tmp_path / "boxes.json", "--json", *flags],
                           capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        return json.loads(p.stdout)["0.25"]

    every, shown = scores(), scores("--seen-only")
    assert (every["tp"], every["predictions"], every["ground_truth"]) == (2, 3, 2)
    # the box on the unseen object is a false positive, as against ScanNet's boxes
    assert (shown["tp"], shown["predictions"], shown["ground_truth"]) == (1, 3, 1)
    assert shown["recall"] == 1.0 and shown["precision"] == pytest.approx(1 / 3)

    del unseen["visible"]
    (tmp_path / "boxes.json").write_text(json.dumps(gt))
    p = subprocess.run([sys.executable, "-m", "parq_runtime.evaluation", tmp_path / "pred.json",
                        tmp_path / "boxes.json", "--seen-only"], capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and "visible" in p.stderr, p.stderr
    assert scores()["ground_truth"] == 2                    # without the flag, no record needed


def eval_files(tmp_path, capsys, pred_boxes=None, gt_boxes=None, pred=None, gt=None):
    """parq-eval's exit code and stderr lines on files made of these box records (or whole
    documents ``pred`` / ``gt``, or raw text when a document is a str)."""
    from parq_runtime.evaluation import main
    if pred is None:
        pred = {"schema": "parq-onnx/detections", "version": 1, "scene": {"boxes": pred_boxes
                if pred_boxes is not None else [box([0, 0, 0.5]).to_json()]}}
    if gt is None:
        gt = {"format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1],
              "boxes": gt_boxes if gt_boxes is not None else [box([0, 0, 0.5]).to_json()]}
    for name, doc in (("pred.json", pred), ("boxes.json", gt)):
        (tmp_path / name).write_text(doc if isinstance(doc, str) else json.dumps(doc))
    capsys.readouterr()
    rc = main([str(tmp_path / "pred.json"), str(tmp_path / "boxes.json"), "--json"])
    return rc, capsys.readouterr().err.strip().splitlines()


def with_key(key, value):
    """Two box records, the second's ``key`` set to ``value`` (deleted when value is ...)."""
    records = [box([0, 0, 0.5]).to_json(), box([2, 0, 0.5]).to_json()]
    if value is ...:
        del records[1][key]
    else:
        records[1][key] = value
    return records


NAN, INF = float("nan"), float("inf")
BAD_BOXES = [("class", 5, "class must be"), ("class", [1], "class must be"),
             ("label", ..., 'missing "label"'), ("label", True, "label must be"),
             ("label", 1.5, "label must be"), ("center", ..., 'missing "center"'),
             ("center", [NAN, 0, 0.5], "center must be three finite numbers"),
             ("center", [1, 2], "center must be three finite numbers"),
             ("center", ["1", "2", "3"], "center must be three finite numbers"),
             ("center", [1e300, 0, 0], "center [1e+300, 0, 0] is beyond 1e+08 m"),
             ("size", [-1.9, -0.7, -0.9], "size must be three positive finite numbers, got "
                                          "[-1.9, -0.7, -0.9]"),
             ("size", [1, 0, 1], "size must be three positive"),
             ("size", [1, INF, 1], "size must be three positive"),
             ("rotation", 1, "rotation must be a 3x3 rotation"),
             ("rotation", [[1, 0], [0, 1]], "rotation must be a 3x3 rotation"),
             ("rotation", (2 * np.eye(3)).tolist(), "rotation must be a 3x3 rotation"),
             ("rotation", np.diag([1.0, 1, -1]).tolist(), "rotation must be a 3x3 rotation"),
             ("score", "high", "score must be a finite number"),
             ("score", NAN, "score must be a finite number"),
             ("yaw", None, "yaw must be a finite number")]


@pytest.mark.parametrize("key, value, message", BAD_BOXES)
@pytest.mark.parametrize("side", ["pred", "gt"])
def test_parq_eval_refuses_a_bad_box_in_one_line(tmp_path, capsys, side, key, value, message):
    """A bad box in either file: exit 2 and one line naming the file, the box and the value
    that is wrong; no traceback, no scores."""
    if side == "pred":
        rc, err = eval_files(tmp_path, capsys, pred_boxes=with_key(key, value))
        where = "pred.json: scene box 1: "
    else:
        rc, err = eval_files(tmp_path, capsys, gt_boxes=with_key(key, value))
        where = "boxes.json: box 1: "
    assert rc == 2 and len(err) == 1, err
    assert where + message in err[0], err


@pytest.mark.parametrize("gt, pred, message", [
    ({"up": [0, 1]}, None, 'boxes.json: "up" must be three finite numbers'),
    ({"up": [0, 0, 0]}, None, 'boxes.json: "up" must be three finite numbers, not all zero'),
    ({"up": [0, NAN, 1]}, None, 'boxes.json: "up" must be three finite numbers'),
    ({"boxes": {}}, None, 'boxes.json: no "boxes" list'),
    ({"boxes": ...}, None, 'boxes.json: no "boxes" list'),
    ({"boxes": [1]}, None, "boxes.json: box 0: not a JSON object"),
    (None, {"scene": ...}, 'pred.json: not a parq-run output (no "scene" section)'),
    (None, {"scene": {"boxes": {}}}, 'pred.json: "scene" has no "boxes" list'),
])
def test_parq_eval_refuses_a_bad_file_in_one_line(tmp_path, capsys, gt, pred, message):
    gt_doc = {"format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1],
              "boxes": [box([0, 0, 0.5]).to_json()]}
    pred_doc = {"schema": "parq-onnx/detections", "version": 1,
                "scene": {"boxes": [box([0, 0, 0.5]).to_json()]}}
    for doc, change in ((gt_doc, gt), (pred_doc, pred)):
        for k, v in (change or {}).items():
            if v is ...:
                del doc[k]
            else:
                doc[k] = v
    rc, err = eval_files(tmp_path, capsys, pred=pred_doc, gt=gt_doc)
    assert rc == 2 and len(err) == 1 and message in err[0], err


@pytest.mark.parametrize("side", ["pred", "gt"])
def test_parq_eval_refuses_json_nested_too_deeply(tmp_path, capsys, side):
    deep = "[" * 100000 + "]" * 100000
    rc, err = eval_files(tmp_path, capsys, **{side: deep})
    name = "pred.json" if side == "pred" else "boxes.json"
    assert rc == 2 and len(err) == 1 and f"{name}: not readable JSON" in err[0], err


def test_parq_eval_takes_rotations_off_by_rounding_and_scores_as_before(tmp_path, capsys):
    """Rotations a little off orthonormal (files round their numbers) are accepted; the
    scores are those of the boxes as given."""
    rounded = box([0, 0, 0.5], yaw=0.3).to_json()
    rounded["rotation"] = (np.asarray(rounded["rotation"]) + 2e-4).tolist()
    rc, err = eval_files(tmp_path, capsys, pred_boxes=[rounded],
                         gt_boxes=[box([0, 0, 0.5], yaw=0.3).to_json(),
                                   box([2, 0, 0.5]).to_json()])
    assert rc == 0 and not err
    twice = (2 * np.eye(3)).tolist()
    rc, err = eval_files(tmp_path, capsys, pred_boxes=[dict(rounded, rotation=twice)])
    assert rc == 2 and "scene box 0: rotation must be" in err[0], err
