"""The state of a training run between two steps, so that an interrupted run continues
(``parq-train OUTPUT --resume``) to the weights the uninterrupted run would have reached, bit
for bit.

A step depends on the model (trainable form, batch-norm statistics included), the AdamW
moments, the numpy generator that orders the snippets and draws the augmentation and the
denoising noise, torch's generator, and the snippets left in the current pass over the data.
:func:`capture` takes all of them, plus the loss history and the running loss sums (so the
log and the checkpoint's history read as one run). The file holds tensors and plain values
only and is read with ``weights_only``: no code is unpickled.

The recipe (seed, data, steps, schedule, objective) is stored beside the state, and a resumed
command must name the same one: a different recipe would continue a run that no command
describes.
"""
from __future__ import annotations

import copy
import pathlib

import numpy as np
import torch
from torch import nn

from parq_runtime.errors import ParqError

FORMAT = "parq-train training state"


def capture(model: nn.Module, optimizer: torch.optim.Optimizer, rng: np.random.Generator,
            order: list, running: dict, history: list, step: int, seconds: float,
            average=None) -> dict:
    """Everything the loop needs to take step ``step`` (0-based: ``step`` steps are done),
    and the weight mean's sums so far when the run keeps one (``average``, a
    :class:`parq_train.average.WeightMean`)."""
    state = {"step": step, "seconds": float(seconds),
             "model": {k: v.detach().clone() for k, v in model.state_dict().items()},
             "optimizer": copy.deepcopy(optimizer.state_dict()),  # AdamW updates in place
             "numpy_rng": rng.bit_generator.state,
             "torch_rng": torch.get_rng_state(),
             "order": [int(i) for i in order],
             "running": {k: float(v) for k, v in running.items()},
             "history": list(history)}
    if average is not None:
        state["average"] = average.state_dict()
    return state


def restore(state: dict, model: nn.Module, optimizer: torch.optim.Optimizer,
            rng: np.random.Generator) -> tuple:
    """Load a :func:`capture` into the loop's objects; returns (step, seconds, order, running,
    history)."""
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    rng.bit_generator.state = state["numpy_rng"]
    torch.set_rng_state(state["torch_rng"])
    return (state["step"], state["seconds"], list(state["order"]), dict(state["running"]),
            list(state["history"]))


def path_for(output) -> pathlib.Path:
    """The state file of the run that writes checkpoint ``output``: its stem + '-state.pt'."""
    output = pathlib.Path(output)
    return output.with_name(f"{output.stem}-state.pt")


def save(path, state: dict, recipe: dict, extra: dict) -> None:
    """Write a state atomically (a crash mid-write leaves the previous state whole).
    ``recipe``: what the command must repeat to resume; ``extra``: records the final
    checkpoint needs (pretraining, minutes of the earlier phases, commands)."""
    path = pathlib.Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, "recipe": recipe, "extra": extra, "state": state}, tmp)
    tmp.replace(path)


def read(path, recipe: dict) -> tuple:
    """(state, extra) of a file :func:`save` wrote for the same ``recipe``; ParqError naming
    the file when it is missing, foreign or unreadable, or was written by another recipe
    (naming the settings that differ)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ParqError(f"{path}: no training state to resume (a run writes it every "
                        f"--snapshot-every steps)")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for files it cannot read
        raise ParqError(f"{path}: not a readable torch file ({type(e).__name__})") from None
    if not isinstance(saved, dict) or saved.get("format") != FORMAT:
        raise ParqError(f"{path}: not a training state written by parq-train")
    differ = sorted(k for k in set(recipe) | set(saved["recipe"])
                    if recipe.get(k) != saved["recipe"].get(k))
    if differ:
        was = ", ".join(f"{k} {saved['recipe'].get(k)!r}" for k in differ)
        raise ParqError(f"{path}: written by another recipe; resume with the same settings "
                        f"({was})")
    return saved["state"], saved["extra"]
