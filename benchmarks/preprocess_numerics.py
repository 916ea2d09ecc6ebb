"""How far other resize filters land from the authors' (PIL BILINEAR, antialiased) on
ScanNet-size frames: 1296x968, padded to 1296x972, resized to 320x240.

Frames: three generated scenes rendered at 1296x968 (parq-synth), so edges and textures are
sharp as in real captures.  Reports the max and mean absolute difference in grey levels of the
uint8 result against PIL, and the time per frame.

    python benchmarks/preprocess_numerics.py
"""
from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
from PIL import Image

import common


def frames():
    from parq_synth import generate

    folder = common.CACHE / "scannet_size"
    if not (folder / "scene_00002" / "boxes.json").exists():
        generate(folder, 3, 4000, frames=2, size=(1296, 968), overwrite=True)
    return [np.asarray(Image.open(p).convert("RGB"))
            for p in sorted(folder.glob("scene_*/color/*.png"))]


def main():
    images = [np.pad(im, ((2, 2), (0, 0), (0, 0))) for im in frames()]
    methods = {
        "PIL BILINEAR (the authors')": lambda im: np.asarray(
            Image.fromarray(im).resize((320, 240), Image.BILINEAR)),
        "cv2 INTER_AREA": lambda im: cv2.resize(im, (320, 240), interpolation=cv2.INTER_AREA),
        "cv2 INTER_LINEAR": lambda im: cv2.resize(im, (320, 240),
                                                  interpolation=cv2.INTER_LINEAR),
    }
    reference = [methods["PIL BILINEAR (the authors')"](im) for im in images]
    print(f"{len(images)} frames 1296x972 -> 320x240")
    print("| method | max abs diff | mean abs diff | ms per frame |")
    print("|---|---:|---:|---:|")
    for name, f in methods.items():
        out = [f(im) for im in images]
        diff = np.abs(np.stack(out).astype(int) - np.stack(reference).astype(int))
        times = []
        for im in images * 5:
            t = time.perf_counter()
            f(im)
            times.append(time.perf_counter() - t)
        print(f"| {name} | {diff.max()} | {diff.mean():.2f} | "
              f"{1000 * statistics.median(times):.2f} |")


if __name__ == "__main__":
    main()
