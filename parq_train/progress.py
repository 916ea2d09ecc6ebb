"""Progress of parq-train's long phases (scene generation, pretraining, training): minutes so
far and the minutes left at the rate so far.

The recipe is a fixed number of steps, so its duration depends on the machine: the demo's
81 minutes were measured on 2-core Xeons (AVX-512); on a 2-core AVX2 EPYC the same steps take
about twice as long (README, "Rebuilding it").  The estimate tells a user within the first
log lines what the command will take on theirs.
"""
from __future__ import annotations


def minutes(elapsed: float, done: int, total: int) -> str:
    """'12.5 min, 30 left' after ``done`` of ``total`` units of work took ``elapsed`` seconds."""
    if done <= 0:
        return f"{elapsed / 60:5.1f} min"
    left = elapsed / done * max(total - done, 0)
    return f"{elapsed / 60:5.1f} min, {left / 60:.0f} left"
