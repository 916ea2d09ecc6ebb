"""A time budget for parq-train (``--minutes``): the number of training steps that ends the
whole command, scene generation and pretraining included, within the budget on this machine.

The demo's recipe is a fixed number of steps, so its duration is the machine's: 89 minutes on
the 2-core AVX-512 EPYC that made the card, about 140 on the 2-core AMX Xeon of 2026-12-07
(README, "Rebuilding it").  With a budget, parq-train measures its own pace over the first
:data:`PLAN_AT` training steps and sets the run's length then, once: the most steps that the
minutes left hold at that pace times :data:`MARGIN`, and never more than ``--steps``.

The plan is made inside the warm-up (the first 500 steps, whose learning rates do not depend on
the run's length when it has at least :data:`MIN_STEPS`), so a run planned to N steps takes
exactly the steps ``--steps N`` takes: the card records N, and ``--steps N`` repeats the run
bit for bit on any machine whose rounding is the same.
"""
from __future__ import annotations

import math

from parq_runtime.errors import ParqError

PLAN_AT = 250
"""Training steps whose pace sets the plan (the progress line's first estimate, too)."""

MIN_STEPS = 5000
"""The fewest steps a plan may give: 10 times the 500-step warm-up, the length from which the
warm-up no longer depends on the number of steps (``min(500, steps // 10)`` in
``train.train``)."""

MARGIN = 1.10
"""Planned seconds a step over the first steps' pace.  Measured: the card's run took 0.230 s
a step over its 19,000 steps against 0.216 over its first 1,000 (1.065, the machine slowing
during the run); the five 3,000-step probes of 2026-12-07 took 0.97-1.05 times the pace of
their first 250 steps (their logs, work/cw)."""

TAIL_SECONDS = 30.0
"""Kept for what follows the last step: folding the batch norms and writing the checkpoint."""


def planned_steps(budget_s: float, elapsed_s: float, done: int, train_s: float,
                  most: int) -> int:
    """Steps for a run that has taken ``elapsed_s`` seconds in all (``train_s`` of them for its
    first ``done`` training steps) to end within ``budget_s``: ``done`` plus what the seconds
    left hold at ``train_s / done`` times MARGIN a step, at most ``most``.  ParqError when that
    is fewer than MIN_STEPS (and fewer than ``most``)."""
    pace = train_s / done
    left = budget_s - elapsed_s - TAIL_SECONDS
    steps = min(most, done + max(0, math.floor(left / (pace * MARGIN))))
    if steps < min(MIN_STEPS, most):
        raise ParqError(
            f"--minutes {budget_s / 60:g}: at {pace:.3f} s a step, the "
            f"{max(left, 0) / 60:.1f} minutes left after {elapsed_s / 60:.1f} hold "
            f"{steps} training steps, fewer than the {MIN_STEPS} a planned run needs; give "
            f"more minutes, or fewer --scenes (generation) or --pretrain-steps")
    return steps
