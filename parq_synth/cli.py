"""parq-synth: write synthetic ScanNet-layout scenes with ground-truth boxes."""
from __future__ import annotations

import argparse
import sys
import time

from parq_runtime.arguments import OneLineParser, integer
from parq_runtime.errors import ParqError

PROG = "parq-synth"


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG,
        description="Generate synthetic indoor scenes (a textured room with 4-10 pieces of "
                    "furniture of the 9 ScanNet classes, seen by a hand-held camera) as "
                    "ScanNet-export folders OUT/scene_<k>/ with colour PNGs, uint16 depth in "
                    "millimetres, instance masks, camera-to-world poses, intrinsics and "
                    "ground-truth boxes (boxes.json, world frame).  Scene k of seed S is "
                    "the same whatever else is generated alongside it.",
        epilog="Example: parq-synth data/train --scenes 200 --seed 0 --frames 60 "
               "--width 160 --height 120")
    p.add_argument("out", metavar="OUT",
                   help="output folder (created if missing); scenes go to OUT/scene_<k>/")
    p.add_argument("--scenes", type=integer, required=True, metavar="N",
                   help="number of scenes to write (>= 1)")
    p.add_argument("--seed", type=integer, required=True, metavar="S",
                   help="dataset seed (>= 0); scene k uses SeedSequence([S, k])")
    p.add_argument("--start", type=integer, default=0, metavar="K",
                   help="index of the first scene (default 0): writes scene_<K> .. "
                        "scene_<K+N-1>, e.g. to extend a dataset or redo one scene alone")
    p.add_argument("--frames", type=integer, default=60, metavar="F",
                   help="frames per scene (>= 1, default 60; about 6-12 cm apart)")
    p.add_argument("--width", type=integer, default=320, metavar="W",
                   help="image width in pixels (16-4096, default 320)")
    p.add_argument("--height", type=integer, default=240, metavar="H",
                   help="image height in pixels (16-4096, default 240)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace scene folders that already exist (default: refuse)")
    p.add_argument("--jobs", type=integer, default=1, metavar="J",
                   help="scenes rendered in parallel processes (default 1)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .writer import generate, scene_name

    t0 = time.perf_counter()

    def progress(result):
        index, objects, seconds, frame_times = result
        if not args.quiet:
            per = sum(frame_times) / max(len(frame_times), 1)
            print(f"{scene_name(index)}: {objects} objects, {args.frames} frames, "
                  f"{seconds:.1f} s ({per * 1000:.0f} ms/frame rendering)", flush=True)

    try:
        results = generate(args.out, args.scenes, args.seed, frames=args.frames,
                           size=(args.width, args.height), start=args.start,
                           overwrite=args.overwrite, jobs=args.jobs, progress=progress)
    except ParqError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted (complete scenes are kept, none is partial)",
              file=sys.stderr)
        return 130
    if not args.quiet:
        print(f"wrote {len(results)} scene(s) to {args.out} in "
              f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
