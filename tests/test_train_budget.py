"""parq-train --minutes: the run's length planned from the pace of its first steps
(parq_train.budget), equal bit for bit to the run of that many steps."""
import pytest
import torch

from conftest import tiny_config
from test_train import tiny_snippets

from parq_runtime.errors import ParqError
from parq_train import budget, train


def test_the_plan_fills_the_minutes_left_at_the_first_steps_pace_with_a_margin():
    # 30 of 90 minutes gone, the first 250 steps took 100 s: 0.4 s a step, planned at 0.44;
    # (5400 - 1800 - 30) / 0.44 = 8113.6 more steps
    assert budget.planned_steps(5400, 1800, 250, 100.0, 19000) == 250 + 8113
    # the minutes hold more than --steps: --steps
    assert budget.planned_steps(5400, 600, 250, 50.0, 19000) == 19000
    # a faster machine plans more steps, in proportion
    assert budget.planned_steps(5400, 1800, 250, 50.0, 30000) == 250 + 16227


def test_a_budget_too_small_for_a_planned_run_is_refused_saying_what_it_holds():
    with pytest.raises(ParqError, match=r"--minutes 90: at 0\.400 s a step, the 3\.5 minutes "
                                        r"left after 86\.0 hold 727 training steps, fewer "
                                        r"than the 5000"):
        budget.planned_steps(5400, 86 * 60, 250, 100.0, 19000)
    # spent before the plan: nothing left, still one clear sentence
    with pytest.raises(ParqError, match="the 0.0 minutes left after 95.0 hold 250"):
        budget.planned_steps(5400, 95 * 60, 250, 100.0, 19000)


def test_a_run_planned_in_its_warm_up_takes_the_steps_of_a_run_of_that_length():
    """Planned after 3 of at most 69 steps to 60, a run's weights and history are those of a
    60-step run, bit for bit (both warm up over 6 steps); the plan is asked once."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    common = dict(seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2, lr=2e-3,
                  log=lambda *_: None, log_every=10)
    asked = []

    def plan(done, seconds):
        asked.append((done, seconds))
        return 60

    planned, planned_history = train.train(config, snippets, steps=69, plan=plan, plan_at=3,
                                           **common)
    fixed, fixed_history = train.train(config, snippets, steps=60, **common)
    assert len(asked) == 1 and asked[0][0] == 3 and asked[0][1] > 0
    a, b = planned.state_dict(), fixed.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    strip = [[{k: v for k, v in h.items() if k != "seconds"} for h in history]
             for history in (planned_history, fixed_history)]
    assert strip[0] == strip[1] and strip[0][-1]["step"] == 60
    # a plan outside [done, steps] is a bug of the caller, not a silent change of schedule
    with pytest.raises(ValueError, match="a plan of 70 steps after 3 of 69"):
        train.train(config, snippets, steps=69, plan=lambda *_: 70, plan_at=3, **common)


def test_a_last_logging_window_shorter_than_the_others_is_averaged_over_its_own_steps():
    """A planned length is rarely a multiple of the logging interval: steps 21-25 of a run
    logged every 10 steps average to what a run logged every 5 gives for the same steps (not
    half of it, as when every window was divided by 10)."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    common = dict(steps=25, seed=0, folds_of_class=[1] * 9, batch_size=2, iterations=2,
                  lr=2e-3, log=lambda *_: None)
    _, by_10 = train.train(config, snippets, log_every=10, **common)
    _, by_5 = train.train(config, snippets, log_every=5, **common)
    assert [h["step"] for h in by_10] == [10, 20, 25] and by_5[-1]["step"] == 25
    assert by_10[-1]["total"] == pytest.approx(by_5[-1]["total"], rel=1e-12)
    assert by_10[-1]["center"] == pytest.approx(by_5[-1]["center"], rel=1e-12)


TINY = ["--scenes", "1", "--frames", "8", "--jobs", "1", "--batch", "1", "--iterations", "1",
        "--snapshot-every", "0", "--seed", "0"]


@pytest.fixture
def short_plans(monkeypatch):
    """parq-train's planning after 3 steps and from 1 step, so a tiny run can be planned."""
    from parq_train import cli

    monkeypatch.setattr(cli, "PLAN_AT", 3)
    monkeypatch.setattr(cli, "MIN_STEPS", 1)
    return cli


def test_parq_train_records_the_planned_steps_and_trains_what_steps_with_them_trains(
        tmp_path, short_plans, monkeypatch):
    from parq_export import checkpoint

    cli = short_plans
    asked = []

    def planned_steps(budget_s, elapsed_s, done, train_s, most):
        asked.append((budget_s, elapsed_s, done, train_s, most))
        return 40

    monkeypatch.setattr(cli, "planned_steps", planned_steps)
    common = [*TINY, "--data", str(tmp_path / "train"), "--pretrain-steps", "0"]
    assert cli.main([str(tmp_path / "a.pt"), *common, "--steps", "49", "--minutes", "90"]) == 0
    budget_s, elapsed_s, done, train_s, most = asked[0]
    assert len(asked) == 1 and (budget_s, done, most) == (5400, 3, 49)
    assert elapsed_s > train_s > 0     # the command's time counts generation and loading too
    record = checkpoint.load(tmp_path / "a.pt").config.extra["training"]
    assert record["steps"] == 40 and record["command"].endswith("--steps 49 --minutes 90")
    assert record["budget"]["minutes"] == 90 and record["budget"]["most_steps"] == 49
    assert record["budget"]["planned_after"] == 3 and record["budget"]["seconds_per_step"] > 0

    assert cli.main([str(tmp_path / "b.pt"), *common, "--steps", "40"]) == 0
    a, b = (checkpoint.load(tmp_path / f"{n}.pt") for n in "ab")
    wa, wb = a.model().state_dict(), b.model().state_dict()
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert "budget" not in b.config.extra["training"]


def test_parq_train_stops_in_one_line_when_the_minutes_cannot_hold_the_run(
        tmp_path, short_plans, capsys):
    """The real plan, a budget spent before training: exit 2, one line that names the
    pretrained backbone left for the next try, and no checkpoint."""
    cli = short_plans
    out = tmp_path / "a.pt"
    capsys.readouterr()
    code = cli.main([str(out), *TINY, "--data", str(tmp_path / "train"), "--pretrain-steps",
                     "2", "--steps", "49", "--minutes", "0.001"])
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("parq-train: error: --minutes 0.001: at ")
    assert f"the pretrained backbone is in {tmp_path / 'a-pretrained.pt'}" in err[0]
    assert not out.exists() and (tmp_path / "a-pretrained.pt").exists()
