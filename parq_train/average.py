"""The uniform mean of a run's weights over the tail of its schedule (``parq-train
--average-from``).

A step of batch 4 moves the weights by one small sample's gradient, so the last step's
weights carry that sample's noise; the mean of the weights at evenly spaced steps of the
schedule's last part (where the cosine learning rate is low and the weights wander about one
place) may average it out. This is stochastic weight averaging over a fixed grid of steps,
with the batch-norm statistics averaged like the weights (not recomputed). On the demo's run
the mean at 12,000, 14,000 and 16,000 steps scored 0.580 / 0.425 on 40 validation scenes
where the last weights scored 0.564 / 0.401, but level with them on 240 held-out scenes
(-0.001 at IoU 0.25, -0.015 at 0.5; docs/demo-experiments.md, "The weights averaged over
the schedule's tail"): the demo keeps its last weights. It changes nothing the run does;
only the weights written at the end.

The steps counted are ``start``, ``start + every``, ... up to the run's last step, which must
be on that grid: the mean then equals the mean of the snapshots a run with
``--snapshot-every every`` writes at those steps and its final weights.
"""
from __future__ import annotations

import torch
from torch import nn


class WeightMean:
    """Running sum of a model's floating-point state (parameters and batch-norm statistics)
    at the steps :meth:`due` names; integer state (batch counts) is taken from the model as
    it ends."""

    def __init__(self, start: int, every: int):
        if start < 1 or every < 1:
            raise ValueError(f"start {start} and every {every} must be positive")
        self.start, self.every = start, every
        self.count = 0
        self.sums: dict[str, torch.Tensor] = {}

    def due(self, steps_done: int) -> bool:
        """Whether the weights after ``steps_done`` steps are counted."""
        return steps_done >= self.start and (steps_done - self.start) % self.every == 0

    def add(self, state: dict) -> None:
        """Count a state dict's tensors as they are now (a model's ``state_dict()``; summed in
        float64)."""
        for name, value in state.items():
            if value.is_floating_point():
                value = value.detach().to(torch.float64)
                if name in self.sums:
                    self.sums[name] += value
                else:
                    self.sums[name] = value.clone()
        self.count += 1

    def mean_state(self, template: dict) -> dict:
        """``template`` (a state dict of the same keys) with its floating-point tensors
        replaced by the mean of what was counted, in their dtypes; the rest kept."""
        if not self.count:
            raise ValueError("no weights were counted")
        return {name: (self.sums[name] / self.count).to(value.dtype) if name in self.sums
                else value for name, value in template.items()}

    def load_into(self, model: nn.Module) -> None:
        """Replace the model's floating-point state by the mean of what was counted."""
        model.load_state_dict(self.mean_state(model.state_dict()))

    def state_dict(self) -> dict:
        """What a saved training state needs to continue the mean (parq_train.resume)."""
        return {"start": self.start, "every": self.every, "count": self.count,
                "sums": {k: v.clone() for k, v in self.sums.items()}}

    def load_state_dict(self, state: dict) -> None:
        if (state["start"], state["every"]) != (self.start, self.every):
            raise ValueError("a saved weight mean of another grid of steps")
        self.count = state["count"]
        self.sums = {k: v.clone() for k, v in state["sums"].items()}

    def record(self) -> dict:
        """What the training record says about it."""
        return {"from": self.start, "every": self.every, "count": self.count}
