"""The README's picture: the demo model's fused scene boxes on four frames of the sample scene,
with the ground truth dashed in white.

    python benchmarks/demo_figure.py [--model models/parq-demo] [--scene models/parq-demo/sample-scene]

Writes models/parq-demo/sample-scene-overlay.png (four frames spread over the walk, 2x2, each
upscaled 2x for legibility) and prints parq-eval's scores of the scene.
"""
from __future__ import annotations

import argparse
import json
import pathlib

import cv2
import numpy as np

import common


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=str(common.ROOT / "models" / "parq-demo"),
                   help="model folder to run (default models/parq-demo)")
    p.add_argument("--scene", default=str(common.ROOT / "models" / "parq-demo" / "sample-scene"),
                   help="capture folder to draw (default the demo's sample scene)")
    p.add_argument("--out", default=str(common.ROOT / "models" / "parq-demo"
                                         / "sample-scene-overlay.png"),
                   help="PNG to write (default the demo's sample-scene-overlay.png)")
    p.add_argument("--iters", type=int, default=None,
                   help="recurrent iterations (default: the model card's run setting)")
    p.add_argument("--queries", type=int, default=None,
                   help="queries (default: the model card's run setting)")
    args = p.parse_args()

    from parq_runtime import Detector, evaluation, readers, scene, visualize

    det = Detector(args.model)
    capture = readers.open_capture(pathlib.Path(args.scene))
    result = scene.run(det, capture, scene.RunSettings(iters=args.iters, queries=args.queries))
    truth, up = evaluation.load_ground_truth(pathlib.Path(args.scene) / "boxes.json")
    metrics = evaluation.evaluate([(result.fusion.boxes, truth, up)], det.classes)
    frames = capture.frames
    tiles = []
    for i in np.linspace(0, len(frames) - 1, 4).round().astype(int):
        f = frames[i]
        image = f.load_image()
        scale = 2
        big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        K = f.intrinsics.copy()
        K[:2] *= scale
        K[:2, 2] += (scale - 1) / 2
        tiles.append(visualize.draw(big, K, f.cam_to_world, result.fusion.boxes, truth,
                                    header=f"frame {f.name}"))
    grid = np.concatenate([np.concatenate(tiles[:2], 1), np.concatenate(tiles[2:], 1)], 0)
    ok, data = cv2.imencode(".png", grid[..., ::-1])
    pathlib.Path(args.out).write_bytes(data.tobytes())
    print(json.dumps({"scene_boxes": len(result.fusion.boxes), "ground_truth": len(truth),
                      **{t: {k: round(m[k], 3) for k in ("precision", "recall", "f1")}
                         for t, m in metrics.items()}}, indent=1))


if __name__ == "__main__":
    main()
