"""parq-synth: write synthetic ScanNet-layout scenes with ground-truth boxes."""
from __future__ import annotations

import argparse
import errno
import pathlib
import sys
import time

from parq_runtime.arguments import (OneLineParser, at_least, at_most, integer,
                                    non_negative_int, positive_int)
from parq_runtime.errors import ParqError

from .scene import MAX_SIZE, MIN_SIZE

PROG = "parq-synth"

# Upper bounds of the counts, checked by the parser before anything is created: a run of more
# is a mistyped number (a scene's frames are allocated at once, every index is checked before
# the first scene is written).  The parser checks the lower bounds too, so that its message
# names the flag; the library checks them again for callers (parq_synth.scene.check_args).
MAX_SCENES = 1_000_000      # --scenes; --start is below it
MAX_FRAMES = 100_000        # --frames
MAX_JOBS = 1024             # --jobs


def folder_name(text: str) -> str:
    """OUT: not empty (an empty path would be the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("the output folder name is empty")
    return text


pixels = at_most(at_least(integer, MIN_SIZE), MAX_SIZE)


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
    p.add_argument("out", metavar="OUT", type=folder_name,
                   help="output folder (created if missing); scenes go to OUT/scene_<k>/")
    p.add_argument("--scenes", type=at_most(positive_int, MAX_SCENES), required=True,
                   metavar="N",
                   help=f"number of scenes to write (1-{MAX_SCENES})")
    p.add_argument("--seed", type=non_negative_int, required=True, metavar="S",
                   help="dataset seed (>= 0); scene k uses SeedSequence([S, k])")
    p.add_argument("--start", type=at_most(non_negative_int, MAX_SCENES - 1), default=0,
                   metavar="K",
                   help=f"index of the first scene (0-{MAX_SCENES - 1}, default 0): writes "
                        "scene_<K> .. scene_<K+N-1>, e.g. to extend a dataset or redo one "
                        "scene alone")
    p.add_argument("--frames", type=at_most(positive_int, MAX_FRAMES), default=60, metavar="F",
                   help=f"frames per scene (1-{MAX_FRAMES}, default 60; about 6-12 cm apart)")
    p.add_argument("--width", type=pixels, default=320, metavar="W",
                   help=f"image width in pixels ({MIN_SIZE}-{MAX_SIZE}, default 320)")
    p.add_argument("--height", type=pixels, default=240, metavar="H",
                   help=f"image height in pixels ({MIN_SIZE}-{MAX_SIZE}, default 240)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace scene folders that already exist (default: refuse)")
    p.add_argument("--jobs", type=at_most(positive_int, MAX_JOBS), default=1, metavar="J",
                   help=f"scenes rendered in parallel processes (1-{MAX_JOBS}, default 1)")
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

    created = first_missing(args.out)
    try:
        try:
            results = generate(args.out, args.scenes, args.seed, frames=args.frames,
                               size=(args.width, args.height), start=args.start,
                               overwrite=args.overwrite, jobs=args.jobs, progress=progress)
        except BaseException:
            remove_empty(args.out, created)     # a run that wrote no scene leaves no folder
            raise
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


def first_missing(out) -> pathlib.Path | None:
    """The outermost folder of ``out``'s path that does not exist yet (the one a run creates
    first), or None when ``out`` exists."""
    def exists(path: pathlib.Path) -> bool:
        try:
            return path.exists() or path.is_symlink()
        except OSError:     # e.g. a name too long: not there
            return False

    path = pathlib.Path(out).absolute()
    if exists(path):
        return None
    while not exists(path.parent) and path.parent != path:
        path = path.parent
    return path


def remove_empty(out, created: pathlib.Path | None) -> None:
    """After a failed run: remove the folders it created (``out`` up to ``created``) while they
    are empty, so that a run that wrote no scene leaves nothing behind."""
    if created is None:
        return
    path = pathlib.Path(out).absolute()
    while True:
        try:
            path.rmdir()
        except (FileNotFoundError, NotADirectoryError):
            pass            # not made (the run failed before it)
        except OSError as e:
            if e.errno != errno.ENAMETOOLONG:
                return      # not empty (scenes or others' files) or not ours to remove
        if path == created or path.parent == path:
            return
        path = path.parent


if __name__ == "__main__":
    sys.exit(main())
