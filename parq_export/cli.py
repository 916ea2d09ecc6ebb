"""parq-export: a PARQ checkpoint -> a model folder (backbone.onnx, layer.onnx, model.json)."""
from __future__ import annotations

import argparse
import pathlib
import sys

from parq_runtime.arguments import OneLineParser, integer
from parq_runtime.errors import ParqError
from parq_runtime.files import os_error


def parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="parq-export",
        description="Export a PARQ checkpoint (the authors' release file, their Lightning "
                    "training checkpoints, or this package's) to ONNX: backbone.onnx, "
                    "layer.onnx and the model card model.json, checked against PyTorch.")
    p.add_argument("checkpoint", type=pathlib.Path, help="checkpoint file (.ckpt / .pt)")
    p.add_argument("-o", "--output", type=pathlib.Path, default=None,
                   help="model folder to write (default: the checkpoint's name without "
                        "extension, beside it)")
    p.add_argument("--opset", type=integer, default=18, choices=(17, 18),
                   help="ONNX opset (default 18)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing model folder (only one that holds nothing but "
                        "an export's backbone.onnx, layer.onnx and model.json)")
    p.add_argument("--quantize", choices=("int8",), default=None,
                   help="int8 convolutions in backbone.onnx (static QDQ, calibrated on "
                        "generated scenes); see docs/speed.md for when it pays")
    p.add_argument("--calibration", type=pathlib.Path, default=None,
                   help="folder of parq-synth scenes to calibrate --quantize with (default: 8 "
                        "scenes generated on the fly)")
    p.add_argument("--no-check", action="store_true",
                   help="skip the check of the graphs against PyTorch (not recommended)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.output or args.checkpoint.with_suffix("")
    if out.resolve() == args.checkpoint.resolve():
        out = args.checkpoint.parent / (args.checkpoint.name + ".onnx")
    try:
        from .export import export
        result = export(args.checkpoint, out, opset=args.opset, check=not args.no_check,
                        overwrite=args.force, quantize=args.quantize,
                        calibration=args.calibration)
    except ParqError as e:
        print(f"parq-export: error: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:    # a path the checks could not foresee (permissions)
        print(f"parq-export: error: {os_error(e)}", file=sys.stderr)
        return ParqError.exit_code
    except KeyboardInterrupt:
        print("parq-export: interrupted (nothing was written)", file=sys.stderr)
        return 130
    print(f"wrote {result.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
