"""Average the weights of checkpoints trained from one start (a "model soup") into one.

The average is a checkpoint like any other, scored the same way:

    python benchmarks/weight_average.py work/soup/b4g3.pt work/b4/b4.pt work/g3/g3.pt
    python benchmarks/snippet_gap.py score work/soup/b4g3.pt work/soup/model

Every floating-point tensor is the plain mean of the inputs' (computed in float64); integer
buffers (BatchNorm's step counts) and the config (snippet gap included) are the first
input's.  The inputs must have the same architecture: the same keys and tensor shapes.  Run of
2026-12-02 (docs/demo-experiments.md, "bfloat16 at batch 4"): the bf16 batch-4 model and the
gap-3 model, both from the same pretrained backbone and seed, averaged to a model worse than
either.
"""
from __future__ import annotations

import argparse
import pathlib
import sys

from parq_export import checkpoint
from parq_runtime.errors import ParqError
from parq_train.average import WeightMean


def average(paths: list) -> checkpoint.Checkpoint:
    """The mean of the checkpoints' floating-point tensors; ParqError if they differ in form."""
    loaded = [checkpoint.load(p) for p in paths]
    first = loaded[0]
    for path, other in zip(paths[1:], loaded[1:]):
        if other.state_dict.keys() != first.state_dict.keys() or any(
                other.state_dict[k].shape != v.shape for k, v in first.state_dict.items()):
            raise ParqError(f"{path}: not the architecture of {paths[0]}")
    mean = WeightMean(start=1, every=1)
    for other in loaded:
        mean.add(other.state_dict)
    return checkpoint.Checkpoint(first.config, mean.mean_state(first.state_dict), first.layout,
                                 "")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("output", type=pathlib.Path, help="checkpoint to write (.pt)")
    p.add_argument("inputs", type=pathlib.Path, nargs="+",
                   help="checkpoints to average (this package's format or any parq-export reads)")
    args = p.parse_args()
    try:
        soup = average(args.inputs)
    except ParqError as e:
        sys.exit(f"weight_average: {e}")
    checkpoint.save(args.output, soup.model(),
                    {"weight_average": [str(p) for p in args.inputs]})
    print(f"{args.output}: mean of {len(args.inputs)} checkpoints")


if __name__ == "__main__":
    main()
