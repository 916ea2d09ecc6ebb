"""The training objective and loop."""
import json
import math
import os
import pathlib

import numpy as np
import pytest
import torch

from parq_export import verify
from parq_export.model import PARQ
from parq_train import loss, train
from parq_train.data import Snippet

from conftest import tiny_config


def _chair(x, score, size=(0.5, 0.8, 0.5)):
    """(a chair Box at (x, 0, 1) of ``size``, axis-aligned, with ``score``; its center): one
    snippet detection as parq_train.validation_runs' records hold it, the local frame the
    world's."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners

    c, s, R = np.array([x, 0.0, 1.0]), np.array(size, dtype=float), np.eye(3)
    return Box(c, s, R, 0.0, 0, "chair", score, box_corners(c, s, R)), c


def _no_floor(n, guess):
    """A tune ``sweep`` for tests without floor classes: none may be looked for."""
    raise AssertionError("no floor classes: no floor is looked for")


def test_matching_hungarian_plus_proximity():
    reference = torch.tensor([[0.0, 0, 1], [0.05, 0, 1], [2, 0, 1], [0.5, 0, 3]])
    prob = torch.full((4, 10), 0.1)
    centers = torch.tensor([[0.0, 0, 1], [2, 0.1, 1]])
    labels = torch.tensor([0, 1])
    q, t = loss.match(reference, prob, centers, labels)
    pairs = sorted(zip(q.tolist(), t.tolist()))
    # Hungarian: 0 -> 0, 2 -> 1; proximity (L1 < 0.2): query 1 -> 0 too; query 3 is far
    assert pairs == [(0, 0), (1, 0), (2, 1)]


def test_rotation_loss_respects_symmetry():
    c, s = math.cos(math.pi), math.sin(math.pi)
    half_turn = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float32)
    target = torch.eye(3)[None]
    pred = half_turn[None]
    assert loss.rotation_loss(pred, target, torch.tensor([2])) < 1e-10
    assert loss.rotation_loss(pred, target, torch.tensor([1])) > 0.5
    assert loss.rotation_loss(pred, target, torch.tensor([36])) < 1e-10


def test_center_weight_scales_only_the_center_term_and_not_the_matching():
    """--center-weight: the total moves by (10 - 5) x the center part; the parts, and so the
    matching behind them, are the same as with the paper's weights."""
    torch.manual_seed(0)
    out = {"logits": torch.randn(1, 6, 10), "reference": torch.rand(1, 6, 3) * 2,
           "center": torch.rand(1, 6, 3) * 2, "size": torch.rand(1, 6, 3) + 0.2,
           "rotation": torch.eye(3).expand(1, 6, 3, 3).clone()}
    target = {"labels": torch.tensor([0, 3]),
              "centers": torch.tensor([[0.5, 0.5, 1], [1.5, 1, 0.5]]),
              "sizes": torch.tensor([[0.5, 0.8, 0.6], [1.0, 1.3, 0.3]]),
              "rotations": torch.eye(3).expand(2, 3, 3).clone()}
    folds = torch.ones(9, dtype=torch.long)
    paper, paper_parts = loss.total_loss([out, out], [target], folds, 9)
    heavy, heavy_parts = loss.total_loss([out, out], [target], folds, 9, {"center": 10.0})
    assert heavy_parts == paper_parts and paper_parts["center"] > 0.1
    assert float(heavy - paper) == pytest.approx(5.0 * paper_parts["center"], rel=1e-6)
    assert loss.WEIGHTS["center"] == 5.0                 # the paper's, not changed in place
    from parq_train.cli import PAPER_CENTER_WEIGHT      # the CLI's torch-free copy of it
    assert PAPER_CENTER_WEIGHT == loss.WEIGHTS["center"]


def test_norm_swap_round_trip_keeps_the_function():
    model = PARQ(tiny_config())
    x = torch.rand(2, 3, 48, 64)
    with torch.no_grad():
        for m in model.modules():
            if hasattr(m, "running_var"):
                m.running_var.uniform_(0.5, 2.0)
                m.running_mean.normal_()
        before = model.backbone(x)
        trainable = train.swap_norms(model, to_trainable=True).eval()
        assert any(isinstance(m, torch.nn.BatchNorm2d) for m in trainable.modules())
        middle = trainable.backbone(x)
        after = train.swap_norms(trainable, to_trainable=False).backbone(x)
    torch.testing.assert_close(middle, before)
    torch.testing.assert_close(after, before)
    assert set(PARQ(tiny_config()).state_dict()) == set(model.state_dict())


def tiny_snippets(config):
    rng = np.random.default_rng(0)
    snippets = []
    for _ in range(2):
        camera, T_local_camera = verify.random_snippet(rng, 3, config)
        w, h = config.image_size
        snippets.append(Snippet(
            "s", rng.integers(0, 256, (3, h, w, 3), dtype=np.uint8), camera, T_local_camera,
            np.array([0, 4]), np.array([[0.3, -1.0, 2.0], [-0.5, -0.8, 3.0]], np.float32),
            np.array([[0.5, 0.8, 0.6], [1.0, 1.3, 0.3]], np.float32),
            np.stack([np.eye(3, dtype=np.float32)] * 2)))
    return snippets


def test_loss_goes_down_on_a_tiny_set():
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    _, history = train.train(config, snippets, steps=60, seed=0, folds_of_class=[1] * 9,
                             batch_size=2, iterations=2, lr=2e-3, log=lambda *_: None,
                             log_every=10)
    first, last = history[0]["total"], history[-1]["total"]
    assert last < 0.6 * first, history


def test_tune_picks_the_threshold_and_region_that_separate_true_from_false_boxes():
    """One snippet, one true box (score 0.9, local center 1 m ahead) and two false ones: a
    confident one far outside the authors' region (4 m ahead) and a weak one (0.4) nearby.
    Only threshold >= 0.4 with a region that excludes z = 4 m scores F1 = 1."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners
    from parq_train import postprocess_search as search

    def box(center, score, label=0):
        c, s, R = np.asarray(center, float), np.array([0.5, 0.8, 0.5]), np.eye(3)
        return Box(c, s, R, 0.0, label, "chair", score, box_corners(c, s, R))

    truth = [box([0.0, 0.0, 1.0], 1.0)]
    snippet = [(box([0.0, 0.0, 1.0], 0.9), np.array([0.0, 0.0, 1.0])),
               (box([0.0, 0.0, 4.0], 0.95), np.array([0.0, 0.0, 4.0])),
               (box([1.0, 0.0, 1.0], 0.4), np.array([1.0, 0.0, 1.0]))]
    records = [([snippet], truth, (0.0, 0.0, 1.0))]
    best, table = search.select(records, ["chair"], thresholds=(0.3, 0.5, 0.8),
                                regions=search.REGIONS)
    assert best["score_threshold"] == 0.5 and best["eval_region"][3] < 4.0
    # one snippet: support 2 or 3 reports nothing; equal F1s go to the authors' fusion
    assert (best["fusion"], best["min_support"]) == ("best", 1)
    best = max(r["f1@0.25"] for r in table)
    assert best == 1.0
    everything = next(r for r in table if r["score_threshold"] == 0.3
                      and r["eval_region"][3] == 10.0 and r["min_support"] == 1)
    assert everything["f1@0.25"] == 0.5     # 1 of 3 predictions right, the one box found


def test_tune_criterion_keeps_iou_50_above_its_floor_then_maximises_iou_25():
    """The sum picks the row with the best F1@0.25 + F1@0.5; with a floor at IoU 0.5 the best
    F1@0.25 among the rows at or above the floor wins, whatever the sum says; with no row at
    or above the floor, the sum decides.  Equal keys keep the first row (the authors')."""
    from parq_train import postprocess_search as search

    rows = [{"name": "precise", "f1@0.25": 0.58, "f1@0.5": 0.41},
            {"name": "reaching", "f1@0.25": 0.61, "f1@0.5": 0.36},
            {"name": "loose", "f1@0.25": 0.63, "f1@0.5": 0.29},
            {"name": "reaching twin", "f1@0.25": 0.61, "f1@0.5": 0.36}]
    assert search.best_of(rows)["name"] == "precise"                     # 0.99 > 0.97 > 0.92
    assert search.best_of(rows, search.Criterion(0.35))["name"] == "reaching"
    assert search.best_of(rows, search.Criterion(0.25))["name"] == "loose"
    assert search.best_of(rows, search.Criterion(0.5))["name"] == "precise"  # none clear: the sum
    assert search.Criterion(0.35).describe() == "max F1@0.25 with F1@0.5 >= 0.35"
    assert search.SUM.describe() == "max F1@0.25 + F1@0.5"


def test_tune_turns_the_floor_on_when_it_helps_and_knows_which_classes_stand():
    """A chair (center 0.4 m up, 0.8 m tall) seen from a camera at eye height in two snippets,
    both times 0.4 m too far along the viewing ray: the ray fusion cannot fix that (F1 0), a
    floor at z = 0 pulls it back (F1 1), so tune chooses the floor for chairs.  A floor the
    sweep puts 0.5 m off is no floor (too far from the boxes' guess): off wins the tie.  A
    display standing on a table is not a floor class."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners
    from parq_train import postprocess_search as search

    camera = np.array([0.0, 0.0, 1.5])
    R = np.stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]], -1)       # object y (up) = world z

    def box(center, name="chair", score=0.9, size=(0.5, 0.8, 0.5)):
        c, s = np.asarray(center, float), np.asarray(size, float)
        label = ["chair", "display"].index(name)
        return Box(c, s, R, 0.0, label, name, score, box_corners(c, s, R), viewpoint=camera)

    truth_center = np.array([3.0, 0.0, 0.4])
    ray = (truth_center - camera) / np.linalg.norm(truth_center - camera)
    seen = box(truth_center + 0.4 * ray)
    records = [([[(seen, seen.center)], [(seen, seen.center)]], [box(truth_center, score=1.0)],
                (0.0, 0.0, 1.0))]
    best, _ = search.select(records, ["chair"], thresholds=(0.5,), regions=search.REGIONS[-1:],
                            fusions=(("ray", 1, 30.0),))
    assert best["f1@0.25"] == 0.0 and best["floor_classes"] == []
    chosen, rows = search.select_floor(records, ["chair"], best, lambda n, guess: [(0.0, 0.1)])
    assert (chosen["floor_classes"], chosen["f1@0.25"]) == (["chair"], 1.0)
    assert rows[0]["floor_classes"] == [] and rows[0]["f1@0.25"] == 0.0
    chosen, _ = search.select_floor(records, ["chair"], best, lambda n, guess: [(0.5, 0.1)])
    assert chosen["floor_classes"] == [] and chosen["f1@0.25"] == 0.0
    on_table = [box([1.0, 1.0, 0.95], "display", size=(0.5, 0.5, 0.1)), box([1.0, 1.0, 0.4])]
    assert search.standing_classes([([], on_table, (0.0, 0.0, 1.0))] + records,
                                   ["chair", "display"]) == ["chair"]


def test_tune_last_pass_moves_threshold_and_support_together_and_keeps_best_on_ties():
    """Chair A is found by two snippets, chair B by one, and a false chair (score 0.55) by
    one: at support 2 only A is reported (F1 2/3); support 1 reports B too, and above 0.55
    nothing false (F1 1), so the last pass picks support 1 at the first threshold that
    drops the false box.  With chair A alone every row ties the given choice, which stays."""
    from parq_train import postprocess_search as search

    box = _chair
    up, a, b, false = (0.0, 0.0, 1.0), box(0.0, 0.9), box(3.0, 0.9), box(6.0, 0.55)
    records = [([[a, b], [a], [false]], [a[0], b[0]], up)]
    best, _ = search.select(records, ["chair"], thresholds=(0.5,), regions=search.REGIONS[-1:],
                            fusions=(("ray", 2, 30.0),))
    assert (best["min_support"], best["f1@0.25"]) == (2, 0.6667)
    chosen, rows = search.select_keep(records, ["chair"], best, sweep=None)
    assert len(rows) == len(search.THRESHOLDS) * 2                    # supports 1 and 2
    assert (chosen["score_threshold"], chosen["min_support"], chosen["f1@0.25"]) == \
        (0.55, 1, 1.0)
    assert chosen["fusion"] == "ray" and chosen["ray_ratio"] == 30.0
    alone = [([[a], [a]], [a[0]], up)]
    best, _ = search.select(alone, ["chair"], thresholds=(0.5,), regions=search.REGIONS[-1:],
                            fusions=(("ray", 2, 30.0),))
    assert search.select_keep(alone, ["chair"], best, sweep=None)[0] is best


def test_tune_chooses_scene_nms_after_the_grid_and_off_on_ties():
    """Two detections of each of two snippets on one chair grow two scene boxes: the grid's
    best keeps both (F1 2/3); scene NMS at the first IoU they exceed reports one (F1 1);
    with nothing to remove, off (the first choice) wins the tie."""
    from parq_train import postprocess_search as search

    box = _chair
    truth = [box(0.0, 1.0)[0]]
    up = (0.0, 0.0, 1.0)
    pair = [box(0.0, 0.9), box(0.2, 0.8)]              # their IoU: 0.3 / 0.7 = 0.43
    records = [([pair, [], pair], truth, up)]           # seen twice: support 2 keeps both
    best, rows = search.select(records, ["chair"], thresholds=(0.5,), regions=search.REGIONS[-1:])
    assert best["f1@0.25"] == 0.6667 and best["scene_nms"] is None
    chosen, rows = search.select_scene_nms(records, ["chair"], best)
    assert [r["scene_nms"] for r in rows] == list(search.SCENE_NMS)
    assert (chosen["scene_nms"], chosen["f1@0.25"]) == (0.0, 1.0)
    assert next(r for r in rows if r["scene_nms"] == 0.3)["f1@0.25"] == 1.0
    alone = [([[box(0.0, 0.9)]], truth, up)]
    best, _ = search.select(alone, ["chair"], thresholds=(0.5,), regions=search.REGIONS[-1:])
    assert search.select_scene_nms(alone, ["chair"], best)[0]["scene_nms"] is None


def test_tune_chooses_the_label_vote_when_it_scores_and_the_authors_rule_on_ties():
    """Three snippets see one table: two call it a table (0.85, 0.85), one a chair (0.9).  The
    best detection's class (the authors' rule) reports a chair, F1 0; the vote (1.7 against
    0.9) a table, F1 1.  With every snippet agreeing, both rules score alike and the authors'
    wins the tie; the chosen row keeps the rest of ``best`` as it was."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners
    from parq_train import postprocess_search as search

    def box(name, score):
        c, s, R = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.8, 0.6]), np.eye(3)
        label = ["chair", "table"].index(name)
        return Box(c, s, R, 0.0, label, name, score, box_corners(c, s, R)), c

    truth = [box("table", 1.0)[0]]
    up = (0.0, 0.0, 1.0)
    records = [([[box("table", 0.85)], [box("chair", 0.9)], [box("table", 0.85)]], truth, up)]
    best = search.candidate(records, ["chair", "table"], 0.5, search.REGIONS[-1], "mean", 2, 10.0,
                            scene_nms=0.1)

    chosen, rows = search.select_labels(records, ["chair", "table"], best, _no_floor)
    assert [(r["labels"], r["f1@0.25"]) for r in rows] == [("best", 0.0), ("vote", 1.0)]
    assert chosen["labels"] == "vote"
    assert {k: chosen[k] for k in search.CHOSEN if k != "labels"} == {
        k: best[k] for k in search.CHOSEN if k != "labels"}
    agreeing = [([[box("table", 0.85)], [box("table", 0.9)]], truth, up)]
    best = search.candidate(agreeing, ["chair", "table"], 0.5, search.REGIONS[-1], "mean", 2, 10.0,
                            scene_nms=0.1)
    chosen, rows = search.select_labels(agreeing, ["chair", "table"], best, _no_floor)
    assert rows[0]["f1@0.25"] == rows[1]["f1@0.25"] == 1.0 and chosen["labels"] == "best"


def test_tune_lowers_the_matching_iou_when_it_joins_an_object_and_keeps_the_authors_on_ties():
    """Two snippets see one chair 0.85 m apart in depth (IoU 0.08): at support 2 the authors'
    matching IoU (0.1) keeps two boxes of support 1 and reports nothing, F1 0; 0.05 joins them
    into one box on the chair, F1 1, and lower IoUs tie with it (the first wins).  With one
    snippet every IoU scores alike and the authors' stays; the rest of ``best`` is kept."""
    from parq_train import postprocess_search as search

    def box(x, score):
        return _chair(x, score, size=(1.0, 1.0, 1.0))

    truth = [box(0.425, 1.0)[0]]
    up = (0.0, 0.0, 1.0)
    records = [([[box(0.0, 0.9)], [box(0.85, 0.9)]], truth, up)]
    best = search.candidate(records, ["chair"], 0.5, search.REGIONS[-1], "mean", 2, 10.0)
    assert (best["match_iou"], best["f1@0.25"]) == (0.1, 0.0)
    chosen, rows = search.select_match(records, ["chair"], best, _no_floor)
    assert [(r["match_iou"], r["f1@0.25"]) for r in rows] == [
        (0.1, 0.0), (0.05, 1.0), (0.02, 1.0), (0.01, 1.0)]
    assert chosen["match_iou"] == 0.05
    assert {k: chosen[k] for k in search.CHOSEN if k != "match_iou"} == {
        k: best[k] for k in search.CHOSEN if k != "match_iou"}
    alone = [([[box(0.425, 0.9)]], truth, up)]
    best = search.candidate(alone, ["chair"], 0.5, search.REGIONS[-1], "mean", 1, 10.0)
    chosen, rows = search.select_match(alone, ["chair"], best, _no_floor)
    assert all(r["f1@0.25"] == 1.0 for r in rows) and chosen["match_iou"] == 0.1


def test_tune_adds_the_second_sampling_grid_when_its_runs_support_an_object():
    """Looks records (run_looks'): one snippet, its runs at two point-sampling grids, each
    plain and mirrored.  The chair is seen by the first grid's plain run and by both of the
    second grid's runs, a false box by the first grid's plain run alone.  At one grid and
    support 2 nothing is reported (F1 0); both grids at support 2 report the chair alone (F1
    1), so two grids win, at the lowest support that does.  Where the second grid's runs see
    nothing new, every row ties with one grid, which wins."""
    from parq_train import postprocess_search as search

    box = _chair
    truth = [box(0.0, 1.0)[0]]
    up = (0.0, 0.0, 1.0)
    first = [([box(0.0, 0.9), box(1.5, 0.9)], False, 0.0), ([], True, 0.0)]
    second = [([box(0.02, 0.9)], False, 0.5), ([box(-0.02, 0.85)], True, 0.5)]
    best = search.row_of(0.5, search.REGIONS[-1], "mean", 2, 10.0, {})
    best.update(match_iou=0.1)
    (phases, support), rows = search.select_phases([([first + second], truth, up)], ["chair"],
                                                   best, _no_floor, mirror=True)
    assert (rows[0]["phases"], rows[0]["min_support"], rows[0]["f1@0.25"]) == (1, 2, 0.0)
    assert [(r["min_support"], r["f1@0.25"]) for r in rows[1:4]] == [
        (1, 0.6667), (2, 1.0), (3, 1.0)]
    assert (phases, support) == (2, 2)
    (phases, support), rows = search.select_phases(
        [([first + [([], False, 0.5), ([], True, 0.5)]], truth, up)], ["chair"],
        dict(best, min_support=1), _no_floor, mirror=True)
    assert rows[0]["f1@0.25"] == 0.6667 and (phases, support) == (1, None)


def test_tune_with_mirror_runs_counts_both_runs_and_scores_alike_in_any_number_of_jobs():
    """Mirror records: each snippet is (plain, mirrored).  The chair is found by both runs of
    the one snippet, a false box by the plain run only; support 2 (runs) keeps the chair
    alone.  The table is the same row for row in 1 or 2 processes and as each candidate
    scored by itself (one fusion serves every support)."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners
    from parq_train import postprocess_search as search

    def box(center, score):
        c, s, R = np.asarray(center, float), np.array([0.5, 0.8, 0.5]), np.eye(3)
        return Box(c, s, R, 0.0, 0, "chair", score, box_corners(c, s, R)), c

    truth = [box([0.0, 0.0, 1.0], 1.0)[0]]
    plain = [box([0.0, 0.0, 1.0], 0.9), box([1.2, 0.0, 1.5], 0.9)]
    mirrored = [box([0.02, 0.0, 1.05], 0.85)]
    records = [([(plain, mirrored)], truth, (0.0, 0.0, 1.0))]
    grid = dict(thresholds=(0.3, 0.95), regions=search.REGIONS[-1:],
                fusions=search.MIRROR_FUSIONS, mirror=True)
    best, table = search.select(records, ["chair"], **grid)
    assert (best["min_support"], best["f1@0.25"], best["score_threshold"]) == (2, 1.0, 0.3)
    ones = next(r for r in table if r["min_support"] == 1 and r["fusion"] == "best")
    assert ones["f1@0.25"] == 0.6667             # the false box is reported: 2 / 3
    assert all(r["f1@0.25"] == 0.0 for r in table if r["min_support"] > 2)
    assert search.select(records, ["chair"], jobs=2, **grid) == (best, table)
    assert table == [search.candidate(records, ["chair"], r["score_threshold"],
                                      r["eval_region"], r["fusion"], r["min_support"],
                                      r["ray_ratio"], mirror=True) for r in table]
    assert {(r["fusion"], r["min_support"]) for r in table} >= {("ray", 4), ("best", 1)}


def test_tune_ranks_queries_by_their_true_and_false_detections():
    """Query 2 finds the chair twice; query 0 once and misfires twice; query 1 only
    misfires (a table box on the chair, and a chair far away); query 3 finds it once but
    below the ranking score, which does not count; query 4 never fires."""
    from parq_runtime.boxes import Box
    from parq_runtime.geometry import box_corners
    from parq_train import validation_runs

    def box(center, score, query, name="chair"):
        c, s, R = np.asarray(center, float), np.array([0.5, 0.8, 0.5]), np.eye(3)
        return (Box(c, s, R, 0.0, 0, name, score, box_corners(c, s, R), query), c)

    truth = [box([0.0, 0.0, 1.0], 1.0, -1)[0]]
    snippets = [[box([0.0, 0.0, 1.0], 0.9, 2), box([0.05, 0.0, 1.0], 0.8, 0),
                 box([0.0, 0.0, 1.0], 0.95, 1, "table"), box([0.0, 0.0, 1.0], 0.6, 3)],
                [box([0.02, 0.0, 1.0], 0.99, 2), box([3.0, 0.0, 1.0], 0.9, 1),
                 box([0.0, 0.0, 4.0], 0.8, 0), box([0.0, 0.0, 5.0], 0.75, 0)]]
    utility = validation_runs.query_utility([(snippets, truth, (0.0, 0.0, 1.0))], 5)
    np.testing.assert_array_equal(utility, [0.0, -1.0, 2.0, 0.0, 0.0])
    assert validation_runs.rank_queries(utility) == [2, 0, 3, 4, 1]


def test_training_is_deterministic_for_a_seed():
    """The same seed gives the same weights bit for bit (what makes rebuild.sh reproduce the
    demo); another seed does not."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)

    def weights(seed):
        model, _ = train.train(config, snippets, steps=4, seed=seed, folds_of_class=[1] * 9,
                               batch_size=2, iterations=2, lr=2e-3, log=lambda *_: None)
        return model.state_dict()

    a, b, c = weights(0), weights(0), weights(1)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_bfloat16_autocast_training_learns_and_keeps_float32_weights():
    """parq-train --bf16: the forward pass runs in bfloat16 (so the weights come out
    different from float32 training), the loss still falls as in float32, and the model
    that comes out is float32 throughout, ready for export."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    kwargs = dict(seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2, lr=2e-3,
                  log=lambda *_: None, log_every=10)
    model, history = train.train(config, snippets, steps=60, bf16=True, **kwargs)
    first, last = history[0]["total"], history[-1]["total"]
    assert last < 0.6 * first, history
    state = model.state_dict()
    assert all(t.dtype == torch.float32 for t in state.values() if t.is_floating_point())
    short_bf16, _ = train.train(config, snippets, steps=2, bf16=True, **kwargs)
    short_fp32, _ = train.train(config, snippets, steps=2, **kwargs)
    a, b = short_bf16.state_dict(), short_fp32.state_dict()
    assert not all(torch.equal(a[k], b[k]) for k in a)


def test_key_dropout_masks_the_same_scores_in_every_form_at_its_rate():
    """parq-train --key-dropout (DropKey): the mask drops each score with the rate asked, and
    every attention form reads it the same way (True: not read), so under one seed the cached,
    fused (the kernel's mask, inverted), folded and reference (nn.MultiheadAttention's mask)
    forms give the same outputs, and those differ from the forms without it."""
    from parq_export.layer import DecoderLayer

    layer = DecoderLayer(32, 4, 64).train()
    layer.set_dropout(0.0, 0.0, 0.1)
    torch.manual_seed(0)
    dropped = layer.dropped_keys((2, 4, 64, 3601), "cpu")
    assert dropped.shape == (2, 4, 64, 3601) and dropped.dtype == torch.bool
    assert abs(dropped.float().mean().item() - 0.1) < 0.002
    assert layer.eval().dropped_keys((2, 4, 64, 3601), "cpu") is None

    config = tiny_config(num_queries=16)
    images, camera, T_local_camera = random_snippet_batch(config)
    model = PARQ(config)
    train.set_dropout(model, 0.0, 0.0, 0.5)
    model.train()
    outputs = {}
    with torch.no_grad():
        for form in ("cached", "fused", "folded", "reference"):
            torch.manual_seed(7)
            outputs[form] = model(images, camera, T_local_camera, iterations=2,
                                  form=form)[-1]["center"]
        train.set_dropout(model, 0.0)
        plain = model(images, camera, T_local_camera, iterations=2)[-1]["center"]
    for form in ("fused", "folded", "reference"):
        torch.testing.assert_close(outputs[form], outputs["cached"], rtol=1e-4, atol=1e-5)
    assert not torch.allclose(outputs["cached"], plain, rtol=1e-3, atol=1e-4)


def random_snippet_batch(config):
    """A batch of one random 3-view snippet for PARQ.forward: images (1, 3, 3, H, W), camera
    and T_local_camera as torch tensors with their batch axis."""
    camera, T_local_camera = verify.random_snippet(np.random.default_rng(1), 3, config)
    w, h = config.image_size
    images = torch.rand(1, 3, 3, h, w)
    return images, torch.from_numpy(camera)[None], torch.from_numpy(T_local_camera)[None]


def test_dropout_acts_in_training_only_and_leaves_the_weights_form_unchanged():
    """parq-train --dropout: in training mode the decoder layer's outputs are random (every
    form), in evaluation mode they are those of the layer without dropout; training with it
    is seeded (the same seed, the same weights), learns, changes the weights, and returns a
    model whose layer has dropout 0 and the same state-dict keys."""
    config = tiny_config(num_queries=16)
    images, camera, T_local_camera = random_snippet_batch(config)
    model = PARQ(config)
    with torch.no_grad():
        plain = model(images, camera, T_local_camera, iterations=2)[-1]["center"]
        # residual branches and FFN; attention weights; DropKey on the cross-attention
        for rates in ((0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (0.0, 0.0, 0.3)):
            train.set_dropout(model, *rates)
            for form in ("cached", "fused", "folded", "reference"):
                model.train()
                noisy = [model(images, camera, T_local_camera, iterations=2,
                               form=form)[-1]["center"] for _ in range(2)]
                assert not torch.allclose(noisy[0], noisy[1]), (rates, form)
                model.eval()
                torch.testing.assert_close(
                    model(images, camera, T_local_camera, iterations=2, form=form)[-1]["center"],
                    plain, rtol=1e-5, atol=1e-5)
    snippets = tiny_snippets(config)
    kwargs = dict(seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2, lr=2e-3,
                  log=lambda *_: None, log_every=10)
    model, history = train.train(config, snippets, steps=60, dropout=0.1, **kwargs)
    assert history[-1]["total"] < 0.6 * history[0]["total"], history
    assert model.layer.decoder.dropout == model.layer.decoder.attention_dropout == 0.0
    a, b, c = (train.train(config, snippets, steps=3, dropout=rate, **kwargs)[0].state_dict()
               for rate in (0.1, 0.1, 0.0))
    assert a.keys() == c.keys() == PARQ(config).state_dict().keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def outputs_and_gradients(model, batch, form: str, keys: tuple, seed: int | None = None):
    """One forward and backward pass of ``model`` on ``batch`` (images, camera,
    T_local_camera) in attention form ``form``, 2 iterations, of a loss that reaches every
    output: (the outputs ``keys`` of every iteration, {parameter name: gradient}).  ``seed``
    seeds torch first, so that dropout draws the same masks in every form."""
    model.zero_grad()
    if seed is not None:
        torch.manual_seed(seed)
    outputs = model(*batch, iterations=2, form=form)
    total = sum(o["center"].sum() + o["logits"].square().sum() for o in outputs)
    total.backward()
    return ([o[k].detach() for o in outputs for k in keys],
            {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})


def test_fused_attention_form_matches_cached_in_outputs_and_gradients():
    """Training uses torch's fused attention kernel (form "fused"); it must compute what the
    cached form (checked against the authors' arithmetic in test_golden) computes."""
    config = tiny_config(num_queries=16)
    images, camera, T_local_camera = random_snippet_batch(config)
    model = PARQ(config)
    results = {form: outputs_and_gradients(model, (images, camera, T_local_camera), form,
                                           ("center", "size", "logits"))
               for form in ("cached", "fused")}
    for a, b in zip(results["cached"][0], results["fused"][0]):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-5)
    grads_cached, grads_fused = results["cached"][1], results["fused"][1]
    assert set(grads_fused) == set(grads_cached)
    assert "layer.decoder.multihead_attn.in_proj_weight" in grads_fused
    for name in grads_cached:
        torch.testing.assert_close(grads_fused[name], grads_cached[name], rtol=1e-4, atol=1e-5)


def test_fused_attention_form_matches_cached_at_the_demos_size_with_dropout():
    """The same at the demo's size, where the fused kernel tiles its 3 x 40 x 30 = 3,600 keys
    (a tiny config fits in one tile), in training mode with the demo's dropout under one seed:
    the fused run that ended 0.03 below the demo (docs/demo-experiments.md, "The fused
    attention kernel") took these same steps up to rounding."""
    from parq_train.cli import demo_config

    config = demo_config()
    images, camera, T_local_camera = random_snippet_batch(config)
    torch.manual_seed(0)
    model = train.swap_norms(PARQ(config), to_trainable=True).train()
    train.set_dropout(model, 0.1)
    results = {form: outputs_and_gradients(model, (images, camera, T_local_camera), form,
                                           ("center", "logits"), seed=5)
               for form in ("cached", "fused")}
    for a, b in zip(results["cached"][0], results["fused"][0]):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-4)
    grads_cached, grads_fused = results["cached"][1], results["fused"][1]
    assert set(grads_fused) == set(grads_cached)
    for name, g in grads_cached.items():
        assert float((grads_fused[name] - g).norm()) <= 1e-4 * float(g.norm()) + 1e-8, name


def test_backbone_learning_rate_scale_zero_freezes_only_the_backbone():
    config = tiny_config(num_queries=16)
    torch.manual_seed(0)
    model = train.swap_norms(PARQ(config), to_trainable=True)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    trained, _ = train.train(config, tiny_snippets(config), steps=3, seed=0,
                             folds_of_class=[1] * 9, batch_size=2, iterations=2, lr=2e-3,
                             log=lambda *_: None, model=model, backbone_lr=0.0)
    after = trained.state_dict()
    weights = [k for k in before if k.startswith("backbone.") and k.endswith("weight")
               and "bn" not in k]
    assert weights and all(torch.equal(after[k], before[k]) for k in weights)
    assert not torch.equal(after["layer.decoder.linear1.weight"],
                           before["layer.decoder.linear1.weight"])


def test_training_scenes_complete_a_cache_and_refuse_one_made_otherwise(tmp_path):
    """parq-train's data folder: missing scenes are generated, scenes made with other
    arguments (here: other frame counts) are an error naming the folder, not silently used."""
    import pytest

    from parq_runtime.errors import ParqError
    from parq_train.data import training_scenes

    root = tmp_path / "train"
    first = training_scenes(root, 1, seed=7, frames=2, size=(32, 24), log=lambda *_: None)
    before = (first[0] / "pose" / "0.txt").read_bytes()
    both = training_scenes(root, 2, seed=7, frames=2, size=(32, 24), log=lambda *_: None)
    assert [f.name for f in both] == ["scene_00000", "scene_00001"]
    assert (both[0] / "pose" / "0.txt").read_bytes() == before
    with pytest.raises(ParqError, match=r"scene_00000: made with other arguments: frames 2 "
                                        r"\(wanted 3\)"):
        training_scenes(root, 2, seed=7, frames=3, size=(32, 24), log=lambda *_: None)


def test_progress_reports_the_minutes_left_at_the_rate_so_far():
    from parq_train.progress import minutes

    assert minutes(120.0, 1, 4) == "  2.0 min, 6 left"      # 2 min a unit, 3 units to go
    assert minutes(600.0, 250, 16000) == " 10.0 min, 630 left"
    assert minutes(60.0, 5, 5) == "  1.0 min, 0 left"
    assert minutes(30.0, 0, 5) == "  0.5 min"                # no rate yet: no estimate


def test_training_snippets_take_views_the_configs_gap_apart(tmp_path):
    """parq-train --gap: a training snippet's views are snippet_gap keyframes apart, the windows
    parq-run forms for a card with that gap, in the middle view's gravity-aligned frame."""
    from parq_runtime import geometry, keyframes
    from parq_runtime.readers import open_capture
    from parq_train.data import scene_snippets, training_scenes

    folder = training_scenes(tmp_path / "train", 1, seed=3, frames=12, size=(64, 48),
                             log=lambda *_: None)[0]
    capture = open_capture(folder, "scannet")
    keys = keyframes.select([f.cam_to_world for f in capture.frames])
    for gap in (1, 2):
        snippets = scene_snippets(folder, tiny_config(snippet_gap=gap), views=3, stride=1)
        windows = keyframes.windows(keys, 3, 1, gap)
        assert len(snippets) == len(windows) > 0
        for s, window in zip(snippets, windows):
            T_world_camera = np.stack([capture.frames[i].cam_to_world for i in window])
            expected = geometry.invert(geometry.snippet_frame(T_world_camera)) @ T_world_camera
            np.testing.assert_allclose(s.T_local_camera, expected, atol=1e-5)


def test_a_saved_pretraining_gives_the_model_that_pretraining_again_gives(tmp_path, capsys):
    """parq-train writes its pretrained backbone beside the checkpoint; --pretrained starts
    from it and trains the same weights, bit for bit, as the run that pretrained; foreign
    files are refused in one line naming them."""
    from parq_export import checkpoint
    from parq_train import cli

    common = ["--seed", "0", "--data", str(tmp_path / "train"), "--scenes", "1", "--frames",
              "8", "--jobs", "1", "--steps", "2", "--batch", "1", "--iterations", "1",
              "--snapshot-every", "0"]
    assert cli.main([str(tmp_path / "a.pt"), "--pretrain-steps", "2", *common]) == 0
    saved = tmp_path / "a-pretrained.pt"
    assert cli.main([str(tmp_path / "b.pt"), "--pretrained", str(saved), *common]) == 0
    a, b = (checkpoint.load(tmp_path / f"{n}.pt") for n in "ab")
    wa, wb = a.model().state_dict(), b.model().state_dict()
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    record = b.config.extra["training"]
    assert record["pretrain_steps"] == 2 and record["pretraining"]["file"] == str(saved)
    assert a.config.extra["training"]["pretraining"]["steps"] == 2

    bare = tmp_path / "bare.pt"
    torch.save({"conv1.weight": torch.zeros(1)}, bare)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    capsys.readouterr()
    for path, message in ((bare, "not a pretrained backbone written by parq-train"),
                          (garbage, "not a readable torch file"),
                          (tmp_path / "missing.pt", "no such pretrained backbone file")):
        assert cli.main([str(tmp_path / "c.pt"), "--pretrained", str(path), *common]) == 2
        # refused before any scene is loaded: the error is the only line
        assert capsys.readouterr().err.startswith(f"parq-train: error: {path}: {message}")
        assert not (tmp_path / "c.pt").exists()


def test_a_pretrained_backbone_for_another_resnet_is_refused_naming_the_file(tmp_path):
    import pytest

    from parq_runtime.errors import ParqError
    from parq_train import pretrain

    narrow, wide = (train.new_model(tiny_config(resnet_width=w), 0) for w in (8, 16))
    path = tmp_path / "narrow-pretrained.pt"
    pretrain.save_backbone(path, narrow.backbone, {"steps": 1, "image_size": [64, 48]})
    state, record = pretrain.read_backbone(path, tiny_config(image_size=(64, 48)))
    assert record["steps"] == 1
    with pytest.raises(ParqError, match=r"narrow-pretrained.pt: made for another backbone"):
        pretrain.set_backbone(wide.backbone, state, path)
    with pytest.raises(ParqError, match=r"pretrained at image size \[64, 48\], this model "
                                        r"takes \[64, 32\]"):
        pretrain.read_backbone(path, tiny_config(image_size=(64, 32)))
    pretrain.set_backbone(narrow.backbone, state, path)


def test_rewriting_a_card_changes_the_card_everywhere_and_nothing_else(tiny_model, tmp_path):
    """card_rewrite: model.json and both graphs' mirrored cards get the change, the graphs'
    nodes and weights are byte-identical, the new hashes hold; bad sources and existing
    outputs are refused with nothing written."""
    import onnx

    from parq_export import card_rewrite
    from parq_runtime import model_card
    from parq_runtime.errors import ParqError

    def update(card):
        card["postprocess"].update(fusion="ray", min_support=2, ray_ratio=3.0, scene_nms=0.1)

    assert model_card.load(tiny_model).scene_nms is None     # exported without: off
    out = tmp_path / "retuned"
    card = card_rewrite.rewrite(tiny_model, out, update)
    loaded = model_card.load(out)
    assert (loaded.fusion, loaded.min_support, loaded.ray_ratio) == ("ray", 2, 3.0)
    assert loaded.scene_nms == 0.1
    assert card == json.loads((out / "model.json").read_text())
    for role in ("backbone", "layer"):
        name = card["graphs"][role]["file"]
        before, after = onnx.load(str(tiny_model / name)), onnx.load(str(out / name))
        assert before.graph.SerializeToString() == after.graph.SerializeToString()
        mirrored = {p.key: json.loads(p.value) for p in after.metadata_props
                    if p.key == model_card.METADATA_KEY}[model_card.METADATA_KEY]
        assert mirrored["postprocess"] == card["postprocess"]
    with pytest.raises(ParqError, match="already exists"):
        card_rewrite.rewrite(tiny_model, out, update)
    with pytest.raises(ParqError, match="not found"):
        card_rewrite.rewrite(tmp_path / "nope", tmp_path / "other", update)

    def breaks(card):
        card["postprocess"]["ray_ratio"] = 0.0
    with pytest.raises(ParqError, match="ray_ratio"):
        card_rewrite.rewrite(tiny_model, tmp_path / "broken", breaks)
    assert not (tmp_path / "broken").exists()


def test_tune_a_model_folder_writes_a_new_folder_with_the_choice(tiny_model, tmp_path):
    """python -m parq_train.tune FOLDER: the chosen row is in the new card, the query order
    kept; an existing output is refused before the detector runs."""
    import parq_synth
    from parq_runtime import model_card
    from parq_train import postprocess_search as search, tune

    parq_synth.generate(tmp_path / "val", 2, 2000, frames=8, size=(64, 48))
    out = tmp_path / "tuned"
    assert tune.main([str(tiny_model), "--data", str(tmp_path / "val"), "-o", str(out),
                      "--queries", "8"]) == 0
    card = model_card.load(out)
    chosen = card.raw["extra"]["postprocess_tuning"]["chosen"]
    for key in search.CHOSEN:
        assert card.raw["postprocess"][key] == chosen[key]
    assert card.raw["run"] == {"iters": 2, "queries": 8, "mirror": False, "phases": 1}
    assert card.raw["query_order"] == json.loads((tiny_model / "model.json").read_text())[
        "query_order"]
    assert tune.main([str(tiny_model), "--data", str(tmp_path / "val"), "-o", str(out)]) == 2
    mirrored = tmp_path / "tuned-mirror"
    assert tune.main([str(tiny_model), "--data", str(tmp_path / "val"), "-o", str(mirrored),
                      "--queries", "8", "--mirror", "--jobs", "2", "--min-f1-50", "0.2"]) == 0
    card = model_card.load(mirrored)
    assert card.raw["run"] == {"iters": 2, "queries": 8, "mirror": True, "phases": 1}
    record = card.raw["extra"]["postprocess_tuning"]
    assert record["mirror"] is True
    # --phase-data: the same rooms at twice the size choose the sampling grids and support,
    # for a model that point-samples (the tiny model's card made to)
    from parq_export import card_rewrite
    point = tmp_path / "point"
    card_rewrite.rewrite(tiny_model, point, lambda card: card["image"].update(filter="point"))
    parq_synth.generate(tmp_path / "val-large", 2, 2000, frames=8, size=(128, 96))
    phased = tmp_path / "tuned-phases"
    assert tune.main([str(point), "--data", str(tmp_path / "val"), "-o", str(phased),
                      "--queries", "8", "--mirror", "--phase-data",
                      str(tmp_path / "val-large")]) == 0
    card = model_card.load(phased)
    phase_record = card.raw["extra"]["postprocess_tuning"]
    assert phase_record["phase_data"] == [str(tmp_path / "val-large")]
    assert card.raw["run"]["phases"] == phase_record["phases"] in (1, 2)
    assert card.raw["postprocess"]["phase_support"] == phase_record["phase_support"]
    assert (phase_record["phase_support"] is None) == (phase_record["phases"] == 1)
    for model, data in ((point, "val"), (tiny_model, "val-large")):   # one grid: refused
        assert tune.main([str(model), "--data", str(tmp_path / "val"), "-o",
                          str(tmp_path / "refused"), "--phase-data", str(tmp_path / data),
                          "--queries", "8"]) == 2
    assert not (tmp_path / "refused").exists()
    assert record["criterion"] == "max F1@0.25 with F1@0.5 >= 0.2"


def test_tune_pools_several_validation_folders(tmp_path):
    """--data takes several folders: their scenes pooled in order, --scenes per folder; a
    folder without scenes is named in the error."""
    import parq_synth
    from parq_runtime.errors import ParqError
    from parq_train import validation_runs

    parq_synth.generate(tmp_path / "a", 2, 2000, frames=4, size=(32, 24))
    parq_synth.generate(tmp_path / "b", 3, 2001, frames=4, size=(32, 24))
    both = validation_runs.validation_folders([tmp_path / "a", tmp_path / "b"], None)
    assert [f.parent.name for f in both] == ["a", "a", "b", "b", "b"]
    firsts = validation_runs.validation_folders([tmp_path / "a", tmp_path / "b"], 1)
    assert firsts == [both[0], both[2]]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ParqError, match="empty: no generated scenes"):
        validation_runs.validation_folders([tmp_path / "a", tmp_path / "empty"], None)


def test_tune_a_checkpoint_records_its_setting_and_a_query_ranking(tiny_checkpoint, tmp_path):
    """python -m parq_train.tune CKPT: the tuned checkpoint carries the run setting it was
    tuned for and a ranking of all learned queries, also when the setting uses all of them
    (the ranking pass is then the tuning pass); both runs rank the queries alike."""
    import parq_synth
    from parq_export import checkpoint
    from parq_train import tune

    parq_synth.generate(tmp_path / "val", 2, 2000, frames=8, size=(64, 48))
    configs = {}
    for queries in (8, 20):                        # 20: the tiny model's learned count
        out = tmp_path / f"tuned{queries}.pt"
        assert tune.main([str(tiny_checkpoint), "--data", str(tmp_path / "val"), "-o",
                          str(out), "--queries", str(queries), "--iters", "1"]) == 0
        configs[queries] = checkpoint.load(out).config
        assert (configs[queries].run_iters, configs[queries].run_queries) == (1, queries)
        assert sorted(configs[queries].query_order) == list(range(20))
        ranking = configs[queries].extra["postprocess_tuning"]["query_ranking"]
        assert ranking["order"] == list(configs[queries].query_order)
    assert configs[8].query_order == configs[20].query_order
    # with --mirror the checkpoint records mirror runs, and its export carries them
    out = tmp_path / "tuned-mirror.pt"
    assert tune.main([str(tiny_checkpoint), "--data", str(tmp_path / "val"), "-o", str(out),
                      "--queries", "8", "--iters", "1", "--mirror"]) == 0
    config = checkpoint.load(out).config
    assert (config.run_iters, config.run_queries, config.run_mirror) == (1, 8, True)
    assert config.query_order == configs[8].query_order    # ranked on plain runs, as before
    assert config.extra["postprocess_tuning"]["mirror"] is True


def test_an_interrupted_run_resumed_from_its_state_gives_the_same_weights(tmp_path):
    """train(save_state=...) hands out the run's whole state at the snapshot steps; a run
    continued from the step-4 state (read back from its file) ends bit for bit where the
    uninterrupted run ends, with the same loss history, also with denoising queries (whose
    noise comes from the same generator)."""
    from parq_train import resume

    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    kwargs = dict(steps=7, seed=0, folds_of_class=[1] * 9, batch_size=1, iterations=2,
                  lr=2e-3, log=lambda *_: None, log_every=3, snapshot_every=2,
                  denoise_scale=0.4)
    states = []
    whole, history = train.train(config, snippets, save_state=states.append, **kwargs)
    assert [s["step"] for s in states] == [2, 4, 6]
    path = tmp_path / "run-state.pt"
    resume.save(path, states[1], {"seed": 0}, {})
    state, _ = resume.read(path, {"seed": 0})
    resumed, resumed_history = train.train(config, snippets, model=train.new_model(config, 5),
                                           state=state, **kwargs)
    a, b = whole.state_dict(), resumed.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    strip = lambda h: [{k: v for k, v in e.items() if k != "seconds"} for e in h]  # noqa: E731
    assert strip(resumed_history) == strip(history)
    # without the state, the same continuation from a fresh model does not get there
    fresh, _ = train.train(config, snippets, model=train.new_model(config, 0),
                           **dict(kwargs, steps=3))
    assert not all(torch.equal(a[k], fresh.state_dict()[k]) for k in a)


def test_parq_train_resume_continues_an_interrupted_command(tmp_path, capsys, monkeypatch):
    """parq-train killed after a state write, then run again with --resume, writes the
    checkpoint the uninterrupted command writes, records the resumption and removes the
    state; a resume with another recipe, or with no state, is refused in one line."""
    from parq_export import checkpoint
    from parq_train import cli, resume

    common = ["--seed", "0", "--data", str(tmp_path / "train"), "--scenes", "1", "--frames",
              "8", "--jobs", "1", "--steps", "5", "--batch", "1", "--iterations", "1",
              "--pretrain-steps", "2", "--snapshot-every", "2"]
    assert cli.main([str(tmp_path / "a.pt"), *common]) == 0
    assert not resume.path_for(tmp_path / "a.pt").exists()

    real_save, writes = resume.save, []

    def save_then_die(*args):
        real_save(*args)
        writes.append(args[0])
        raise KeyboardInterrupt

    monkeypatch.setattr(resume, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        cli.main([str(tmp_path / "b.pt"), *common])
    monkeypatch.setattr(resume, "save", real_save)
    assert writes == [tmp_path / "b-state.pt"] and not (tmp_path / "b.pt").exists()
    capsys.readouterr()
    assert cli.main([str(tmp_path / "b.pt"), *common, "--lr", "1e-3", "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "written by another recipe" in err and "lr 0.0005" in err
    assert cli.main([str(tmp_path / "b.pt"), *common, "--resume"]) == 0
    assert "resuming" in capsys.readouterr().err
    a, b = (checkpoint.load(tmp_path / f"{n}.pt") for n in "ab")
    wa, wb = a.model().state_dict(), b.model().state_dict()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    record = b.config.extra["training"]
    assert record["resumed"][0]["step"] == 2 and record["command"].endswith("--snapshot-every 2")
    without_minutes = lambda r: {k: v for k, v in r.items() if k != "minutes"}  # noqa: E731
    assert without_minutes(record["pretraining"]) == without_minutes(
        a.config.extra["training"]["pretraining"])
    assert not resume.path_for(tmp_path / "b.pt").exists()
    assert cli.main([str(tmp_path / "b.pt"), *common, "--resume"]) == 2
    assert "no training state to resume" in capsys.readouterr().err


def test_parq_train_queries_sets_the_learned_queries_and_the_card_records_them(tmp_path):
    """--queries N trains N reference points and records N in the checkpoint's training
    record and in the recipe a --resume must repeat."""
    from parq_export import checkpoint
    from parq_train import cli

    out = tmp_path / "q.pt"
    assert cli.main([str(out), "--seed", "0", "--data", str(tmp_path / "train"), *TINY_RUN,
                     "--queries", "5"]) == 0
    loaded = checkpoint.load(out)
    assert loaded.config.num_queries == 5
    assert loaded.model().refpoint.weight.shape == (5, 3)
    assert loaded.config.extra["training"]["queries"] == 5
    recipe = cli.recipe_of(cli.parser().parse_args([str(out), "--queries", "5"]))
    assert recipe["queries"] == 5
    # the demo's 64 leaves the recipe as it was, so that older states still resume
    assert "queries" not in cli.recipe_of(cli.parser().parse_args([str(out)]))


def test_parq_train_image_size_renders_trains_and_records_that_size(tmp_path, capsys):
    """--image-size WxH renders the training scenes at that size, trains a network whose input
    it is, and puts it in the recipe a --resume must repeat; scenes of another size are
    refused, not resampled into the training set."""
    from parq_export import checkpoint
    from parq_train import cli

    data = str(tmp_path / "train")
    out = tmp_path / "s.pt"
    assert cli.main([str(out), "--seed", "0", "--data", data, *TINY_RUN,
                     "--image-size", "64x48"]) == 0
    assert tuple(checkpoint.load(out).config.image_size) == (64, 48)
    scene = json.loads(next((tmp_path / "train").glob("*/scene.json")).read_text())
    assert (scene["width"], scene["height"]) == (64, 48)
    assert cli.recipe_of(cli.parser().parse_args([str(out), "--image-size", "64x48"]))[
        "image_size"] == [64, 48]
    capsys.readouterr()
    assert cli.main([str(tmp_path / "t.pt"), "--data", data, *TINY_RUN]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"width 64 (wanted {cli.DEMO_IMAGE_SIZE[0]})" in err


# ------------------------------------------------------------ parq-train's argument checks

TINY_RUN = ["--scenes", "1", "--frames", "8", "--jobs", "1", "--steps", "1", "--batch", "1",
            "--iterations", "1", "--pretrain-steps", "0", "--snapshot-every", "0"]


@pytest.fixture
def no_work(monkeypatch):
    """parq-train's first work (setting threads, generating scenes) fails the test: a bad
    argument must be refused before it."""
    import parq_train.data

    def started(*args, **kwargs):
        raise AssertionError("parq-train started work before refusing its arguments")

    monkeypatch.setattr(parq_train.data, "training_scenes", started)
    monkeypatch.setattr(torch, "set_num_threads", started)


def refused(argv, capsys):
    """(exit code, stderr) of parq-train ``argv``, parser errors included."""
    from parq_train import cli

    capsys.readouterr()
    try:
        code = cli.main(argv)
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr().err


def assert_one_line(code, err, needle):
    assert code == 2, err
    assert err.startswith("parq-train: error: ") and err.count("\n") == 1, err
    assert needle in err and "Traceback" not in err, err


@pytest.mark.parametrize("output, needle", [
    ("adir", "adir: is a folder, expected a file name"),
    ("nodir/x.pt", "nodir: folder does not exist"),
    ("", "argument OUTPUT: the checkpoint path is empty"),
    (".", "names a folder, expected a checkpoint file name"),
    ("new/", "names a folder, expected a checkpoint file name"),
    ("adir/..", "names a folder, expected a checkpoint file name"),
    ("adir/x.pt", "x-state.pt: is a folder, and parq-train writes this file beside"),
    ("a" * 250 + ".pt", "cannot write there (File name too long)"),
])
def test_parq_train_refuses_an_unwritable_output_before_any_work(
        output, needle, tmp_path, capsys, monkeypatch, no_work):
    """OUTPUT (and the state file beside it) is checked before scenes are generated: an
    existing folder, a missing folder, an empty path or one naming a folder are one line, exit
    2, and nothing is written (no data folder, no checkpoint)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "adir" / "x-state.pt").mkdir(parents=True)
    code, err = refused([output, "--data", "train", *TINY_RUN], capsys)
    assert_one_line(code, err, needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]
    assert [p.name for p in (tmp_path / "adir").iterdir()] == ["x-state.pt"]


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_parq_train_tries_the_output_folder_rather_than_trusting_its_permissions(
        tmp_path, capsys, no_work):
    """/proc takes no files, though access() tells root it is writable."""
    code, err = refused(["/proc/x.pt", "--data", str(tmp_path / "train"), *TINY_RUN], capsys)
    assert_one_line(code, err, "/proc/x.pt: cannot write there")
    assert not (tmp_path / "train").exists()


@pytest.mark.parametrize("flag, needle", [
    (["--seed", "-1"], "--seed: -1 must not be negative"),
    (["--seed", str(2 ** 64)], "--seed: 18446744073709551616 must be at most"),
    (["--lr", "inf"], "--lr: inf is not a finite number"),
    (["--lr", "nan"], "--lr: nan is not a finite number"),
    (["--lr", "0"], "--lr: 0.0 must be above 0"),
    (["--backbone-lr", "inf"], "--backbone-lr: inf is not a finite number"),
    (["--denoise", "inf"], "--denoise: inf is not a finite number"),
    (["--denoise", "nan"], "--denoise: nan is not a finite number"),
    (["--denoise-class-weight", "inf"], "--denoise-class-weight: inf is not a finite number"),
    (["--dense-weight", "inf"], "--dense-weight: inf is not a finite number"),
    (["--dense-weight", "-1"], "--dense-weight: -1.0 must not be negative"),
    (["--threads", "100000000"], "--threads: 100000000 must be at most 1024"),
    (["--jobs", "5000"], "--jobs: 5000 must be at most 1024"),
    (["--scenes", "100000000"], "--scenes 100000000: at most 1000000"),
    (["--frames", "100000000000"], "--frames 100000000000: at most 100000"),
    (["--iterations", "1001"], "--iterations 1001: at most 1000"),
    (["--queries", "1025"], "--queries 1025: at most 1024"),
    (["--queries", "0"], "--queries: 0 must be"),
    (["--gap", "4"], "--frames 8: a scene needs at least 9 frames"),
    (["--frames", "2"], "--frames 2: a scene needs at least 3 frames"),
    (["--data", ""], "--data: the path is empty"),
    (["--pretrained", ""], "--pretrained: the path is empty"),
    (["--average-from", "-1"], "--average-from: -1 must not be negative"),
    (["--average-from", "2"], "--average-from 2: the last step (--steps 1) must be 2 plus a "),
    (["--steps", "5", "--average-from", "2"], "must be 2 plus a multiple of --average-every"),
    (["--average-every", "0"], "--average-every: 0 must be"),
    (["--dropout", "1"], "--dropout: 1.0 must be at least 0 and below 1"),
    (["--attention-dropout", "nan"], "--attention-dropout: nan must be at least 0 and below 1"),
    (["--key-dropout", "1"], "--key-dropout: 1.0 must be at least 0 and below 1"),
    (["--center-weight", "-2"], "--center-weight: -2.0 must not be negative"),
    (["--minutes", "0"], "--minutes: 0.0 must be above 0"),
    (["--minutes", "inf"], "--minutes: inf is not a finite number"),
    (["--minutes", "90"], "--minutes: --steps 1 is below the 5000 a planned run needs"),
    (["--minutes", "90", "--steps", "5000", "--resume"], "--minutes: not with --resume"),
    (["--minutes", "90", "--steps", "6000", "--average-from", "2000"],
     "--minutes: not with --average-from"),
    (["--image-size", "190x144"], "--image-size: 190x144: width and height must be multiples of 4"),
    (["--image-size", "192"], "--image-size: '192': expected WIDTHxHEIGHT"),
    (["--image-size", "28x28"], "width and height must be multiples of 4 from 32 to 4096"),
])
def test_parq_train_refuses_bad_numbers_before_any_work(flag, needle, tmp_path, capsys,
                                                        monkeypatch, no_work):
    monkeypatch.chdir(tmp_path)
    code, err = refused(["x.pt", *TINY_RUN, "--data", "train", *flag], capsys)
    assert_one_line(code, err, needle)
    assert not any(tmp_path.iterdir())


def test_parq_train_checks_pass_for_a_good_command_and_leave_nothing(tmp_path):
    from parq_train import cli

    args = cli.parser().parse_args([str(tmp_path / "x.pt"), *TINY_RUN, "--seed", str(2 ** 64 - 1),
                                    "--pretrain-steps", "3", "--snapshot-every", "2",
                                    "--denoise", "0.5", "--backbone-lr", "0",
                                    "--average-from", "1", "--average-every", "3"])
    cli.check_arguments(args)
    assert not any(tmp_path.iterdir())


def test_parq_train_says_so_when_the_scenes_hold_no_snippet(tmp_path, capsys, monkeypatch):
    """Scenes whose keyframes are too few for one snippet: one line, not a numpy error."""
    import parq_train.data

    monkeypatch.setattr(parq_train.data, "training_scenes", lambda *args, **kwargs: [])
    code, err = refused([str(tmp_path / "x.pt"), *TINY_RUN, "--data", str(tmp_path / "t")],
                        capsys)
    assert code == 2 and "Traceback" not in err
    assert err.splitlines()[-1].startswith("parq-train: error: ")
    assert "hold no snippet" in err and not (tmp_path / "x.pt").exists()


def test_a_checkpoint_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """Checkpoints (parq-train's, its snapshots, every other writer's) go to a temporary file
    renamed into place: a write that fails leaves an earlier checkpoint as it was and no
    temporary file."""
    import os

    from parq_export import checkpoint
    from parq_runtime import files
    from parq_runtime.errors import ParqError

    model = PARQ(tiny_config()).eval()
    path = tmp_path / "x.pt"
    checkpoint.save(path, model, {"step": 1})
    assert checkpoint.load(path).config == model.config
    before = path.read_bytes()
    real_fdopen = os.fdopen

    class FullDisk:             # the disk fills up halfway through the write
        def __init__(self, fd, mode):
            self.file = real_fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def write(self, data):
            self.file.write(data[:len(data) // 2])
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(files.os, "fdopen", FullDisk)
    with pytest.raises(ParqError, match="x.pt: could not write .No space left on device"):
        checkpoint.save(path, model, {"step": 2})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["x.pt"]


def test_parq_train_refuses_a_batch_larger_than_its_snippets(tmp_path, capsys, monkeypatch):
    """A step cannot take more snippets than there are: one line, not smaller batches."""
    import parq_train.data

    monkeypatch.setattr(parq_train.data, "training_scenes", lambda *args, **kwargs: [])
    monkeypatch.setattr(parq_train.data, "load_scenes", lambda *args, **kwargs: [None] * 3)
    argv = [str(tmp_path / "x.pt"), *TINY_RUN, "--data", str(tmp_path / "t")]
    code, err = refused([*argv[:-2], "--batch", "4", *argv[-2:]], capsys)
    assert code == 2 and "Traceback" not in err
    assert err.splitlines()[-1] == ("parq-train: error: --batch 4: the 0 training scenes hold "
                                    "only 3 snippets; lower --batch or raise --scenes")
    assert not (tmp_path / "x.pt").exists()


def test_parq_train_defaults_are_the_shipped_demo_recipe():
    """`parq-train OUT` with no other flag trains what models/parq-demo was trained with, so
    the one command with a seed is the demo's recipe (its card records every setting)."""
    from parq_train import cli

    card = json.loads((pathlib.Path(__file__).parents[1] / "models" / "parq-demo"
                       / "model.json").read_text())
    record = card["extra"]["training"]
    args = cli.parser().parse_args(["out.pt"])
    assert (args.seed, args.scenes, args.frames) == (record["seed"], record["data"]["scenes"],
                                                     record["data"]["frames"])
    assert args.pretrain_steps == record["pretrain_steps"]
    settings = cli.settings_record(args)
    assert settings["queries"] == card["config"]["num_queries"]
    assert list(args.image_size) == [card["image"]["width"], card["image"]["height"]]
    assert {k: record[k] for k in settings} == settings
    assert (settings["precision"], settings["attention"], settings["average"]) == (
        "float32", "cached", None)
