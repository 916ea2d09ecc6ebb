"""The worst differences from the authors' own outputs (tests/golden/official-case), per
attention form: the README's "Reproducing the authors" table.

    python benchmarks/golden_errors.py

tests/test_golden.py asserts the same numbers against the tolerances; this prints them.
Sizes are compared relatively, leaving out queries whose top two class logits are within
1e-3 of each other (the size depends on the argmax class), as the golden README says.
"""
from __future__ import annotations

import json

import numpy as np
from PIL import Image

import common
from parq_runtime.detector import Detector

CASE = common.GOLDEN / "official-case"
ROWS = (("center", "centers (m)", "1e-4"), ("rotation", "rotation entries", "1e-3"),
        ("logits", "logits", "1e-3"), ("size", "sizes (relative)", "1e-3"))


def worst_errors(det: Detector, form: str) -> dict:
    meta = json.loads((CASE / "case.json").read_text())
    expected = np.load(CASE / "expected.npz")
    images = [np.asarray(Image.open(CASE / f"{i}.png").convert("RGB"))
              for i in range(meta["views"])]
    result = det.detect(images, expected["intrinsics"], expected["cam_to_world"],
                        iters=meta["iterations"], queries=meta["queries"], form=form)
    worst = dict.fromkeys([name for name, _, _ in ROWS], 0.0)
    for l, it in enumerate(result.iterations):
        top2 = np.sort(expected[f"iter{l}_logits"], -1)[:, -2:]
        clear = top2[:, 1] - top2[:, 0] > 1e-3
        for name in ("center", "rotation", "logits"):
            diff = np.abs(getattr(it, name) - expected[f"iter{l}_{name}"]).max()
            worst[name] = max(worst[name], float(diff))
        ratio = it.size[clear] / expected[f"iter{l}_size"][clear]
        worst["size"] = max(worst["size"], float(np.abs(ratio - 1).max(initial=0.0)))
    return worst


def main():
    det = Detector(common.official_model())
    errors = {form: worst_errors(det, form) for form in ("cached", "folded")}
    print("| output, worst over 8 iterations x 256 queries | cached form | folded form "
          "| tolerance |")
    print("|---|---:|---:|---:|")
    for name, label, tolerance in ROWS:
        print(f"| {label} | {errors['cached'][name]:.1e} | {errors['folded'][name]:.1e} "
              f"| {tolerance} |")


if __name__ == "__main__":
    main()
