"""Peak memory of parq-run on a long video versus a short one: frames must stream from disk.

Writes two ScanNet-layout captures of tiny 64x48 noise frames (16 distinct PNGs, hard-linked
into color/, so the captures cost almost no disk), walking 15 cm a frame so that every frame is
a keyframe and every frame is read by the detector, then runs parq-run on each in its own
process and reads that process's peak resident memory (``ru_maxrss`` of
``getrusage(RUSAGE_CHILDREN)`` in a wrapper process that runs nothing else).

    python benchmarks/memory_long_video.py                 # 200 and 2000 frames, tiny model
    python benchmarks/memory_long_video.py --model models/parq-demo --frames 200 2000

Without --model a tiny model is exported first (needs the export extra: torch).  The bar: the
longest capture's peak within 10% of the shortest's; exit status 1 otherwise.  Results are
recorded in docs/readers.md.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
BAR = 1.10

WRAPPER = """
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:]).returncode
seconds = time.perf_counter() - start
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, code, seconds)
"""


def tiny_model(folder: pathlib.Path) -> pathlib.Path:
    """The test suite's tiny model (tests/conftest.py: tiny_config), exported to ``folder``."""
    import torch

    from parq_export import checkpoint
    from parq_export.config import PARQConfig
    from parq_export.export import export
    from parq_export.model import PARQ

    torch.manual_seed(0)
    model = PARQ(PARQConfig(resnet_depth=18, resnet_width=8, fpn_channels=16, heads=2,
                            ffn_dim=32, num_queries=20, ray_samples=8, image_size=(64, 48)))
    with torch.no_grad():
        model.refpoint.weight.uniform_(-2.5, 2.5)
    checkpoint.save(folder / "tiny.pt", model)
    export(folder / "tiny.pt", folder / "tiny_model", log=lambda *_: None)
    return folder / "tiny_model"


def write_capture(folder: pathlib.Path, frames: int, size=(64, 48), pool: int = 16):
    from PIL import Image

    from parq_runtime.geometry import camera_pose

    rng = np.random.default_rng(0)
    for sub in ("color", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    w, h = size
    K = np.eye(4)
    K[0, 0] = K[1, 1] = 0.9 * w
    K[0, 2], K[1, 2] = w / 2 - 0.5, h / 2 - 0.5
    np.savetxt(folder / "intrinsic" / "intrinsic_color.txt", K)
    sources = []
    for k in range(pool):
        p = folder / f"noise{k}.png"
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(p)
        sources.append(p)
    for i in range(frames):
        target = folder / "color" / f"{i}.png"
        try:
            os.link(sources[i % pool], target)
        except OSError:
            target.write_bytes(sources[i % pool].read_bytes())
        # a 15 cm step a frame around a 30 m loop: every frame is a keyframe
        a = 0.15 * i / 5.0
        pose = camera_pose([5 * np.cos(a), 5 * np.sin(a), 1.5], a + np.pi / 2, np.radians(15))
        np.savetxt(folder / "pose" / f"{i}.txt", pose)


def measure(capture: pathlib.Path, model: pathlib.Path, out: pathlib.Path, threads: int):
    cmd = [sys.executable, "-c", WRAPPER, sys.executable, "-m", "parq_runtime.cli",
           str(capture), "--model", str(model), "-q", "-o", str(out), "--threads", str(threads)]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if p.returncode != 0:
        raise SystemExit(f"wrapper failed: {p.stderr}")
    kib, code, seconds = p.stdout.split()
    if int(code) != 0:
        raise SystemExit(f"parq-run failed on {capture} (exit {code})")
    data = json.loads(out.read_text())
    return int(kib) / 1024.0, float(seconds), len(data["snippets"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=pathlib.Path, default=None,
                   help="model folder (default: export the tests' tiny model first)")
    p.add_argument("--frames", type=int, nargs="+", default=[200, 2000],
                   help="capture lengths to compare (default 200 2000)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads (default 1)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="parq-memory-") as tmp:
        tmp = pathlib.Path(tmp)
        model = args.model or tiny_model(tmp)
        rows = []
        for n in args.frames:
            start = time.perf_counter()
            write_capture(tmp / f"capture{n}", n)
            written = time.perf_counter() - start
            mib, seconds, snippets = measure(tmp / f"capture{n}", model, tmp / f"{n}.json",
                                             args.threads)
            rows.append((n, snippets, mib, seconds, written))
            print(f"{n:6d} frames  {snippets:5d} snippets  peak RSS {mib:7.1f} MiB  "
                  f"parq-run {seconds:6.1f} s  (capture written in {written:.1f} s)",
                  flush=True)
    base, last = rows[0][2], rows[-1][2]
    ratio = last / base
    ok = ratio <= BAR
    print(f"peak RSS {rows[-1][0]} frames / {rows[0][0]} frames = {ratio:.3f} "
          f"({'within' if ok else 'ABOVE'} the {BAR:.2f} bar)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
