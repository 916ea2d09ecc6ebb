"""parq-train --average-from: the mean of the weights over the schedule's tail
(parq_train.average)."""
import pytest
import torch

from parq_train import resume, train
from parq_train.average import WeightMean

from conftest import tiny_config
from test_train import tiny_snippets

RUN = dict(steps=6, seed=0, folds_of_class=[1] * 9, batch_size=1, iterations=2, lr=2e-3,
           log=lambda *_: None, log_every=3)


def test_the_grid_counts_start_and_every_step_after_it():
    mean = WeightMean(start=4, every=2)
    assert [n for n in range(1, 11) if mean.due(n)] == [4, 6, 8, 10]
    for start, every in ((0, 2), (4, 0)):
        with pytest.raises(ValueError):
            WeightMean(start, every)


def test_the_mean_is_of_the_floating_point_state_and_keeps_the_integer_counts():
    model = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.BatchNorm1d(2))
    mean, seen = WeightMean(1, 1), []
    for k in range(3):
        with torch.no_grad():
            for p in model.parameters():
                p.fill_(float(k))
            model[1].running_var.fill_(2.0 ** k)
        model[1].num_batches_tracked.fill_(10 + k)
        seen.append({n: v.clone() for n, v in model.state_dict().items()})
        mean.add(model.state_dict())
    mean.load_into(model)
    state = model.state_dict()
    assert torch.equal(state["0.weight"], torch.full((2, 3), 1.0))
    assert torch.allclose(state["1.running_var"], torch.full((2,), 7 / 3))
    assert state["1.num_batches_tracked"].item() == 12 and mean.count == 3


def test_a_run_with_the_mean_takes_the_same_steps_and_writes_the_snapshots_mean():
    """Averaging from step 2 every 2 steps of 6: the weights are the mean of the snapshots at
    steps 2 and 4 and of the last weights of the same run without the mean, and the loss
    history is that run's (the mean changes nothing the run does)."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    snapshots = {}
    last, history = train.train(config, snippets, snapshot_every=2,
                                snapshot=lambda m, step: snapshots.__setitem__(step, m), **RUN)
    assert sorted(snapshots) == [2, 4]
    averaged, averaged_history = train.train(config, snippets, average_from=2,
                                             average_every=2, **RUN)
    assert averaged_history == [dict(e, seconds=a["seconds"])
                                for e, a in zip(history, averaged_history)]
    runs = [snapshots[2].state_dict(), snapshots[4].state_dict(), last.state_dict()]
    got = averaged.state_dict()
    assert got.keys() == runs[0].keys()
    moved = 0
    for name, value in got.items():
        expected = sum(r[name].double() for r in runs) / 3
        torch.testing.assert_close(value, expected.to(value.dtype), rtol=1e-6, atol=1e-7)
        moved += not torch.equal(value, runs[-1][name])
    assert moved > len(got) // 2      # most tensors moved during the tail: a real mean
    with pytest.raises(ValueError, match="not on the weight mean's grid"):
        train.train(config, snippets, average_from=3, average_every=2, **RUN)


def test_a_resumed_run_continues_the_mean_bit_for_bit(tmp_path):
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)
    kwargs = dict(RUN, average_from=2, average_every=2, snapshot_every=2)
    states = []
    whole, _ = train.train(config, snippets, save_state=states.append, **kwargs)
    assert states[1]["step"] == 4 and states[1]["average"]["count"] == 2
    path = tmp_path / "run-state.pt"
    resume.save(path, states[1], {"seed": 0}, {})
    state, _ = resume.read(path, {"seed": 0})
    resumed, _ = train.train(config, snippets, model=train.new_model(config, 5), state=state,
                             **kwargs)
    a, b = whole.state_dict(), resumed.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_parq_train_records_the_mean_it_wrote(tmp_path):
    """The checkpoint's training record names the steps counted; without the flag, none."""
    from parq_export import checkpoint
    from parq_train import cli

    common = [str(tmp_path / "a.pt"), "--seed", "0", "--data", str(tmp_path / "train"),
              "--scenes", "1", "--frames", "8", "--jobs", "1", "--steps", "4", "--batch", "1",
              "--iterations", "1", "--pretrain-steps", "0", "--snapshot-every", "0"]
    assert cli.main([*common, "--average-from", "2", "--average-every", "2"]) == 0
    record = checkpoint.load(tmp_path / "a.pt").config.extra["training"]
    assert record["average"] == {"from": 2, "every": 2, "count": 2}
    assert record["command"].endswith("--average-from 2 --average-every 2")
    assert cli.main(common) == 0
    assert checkpoint.load(tmp_path / "a.pt").config.extra["training"]["average"] is None
