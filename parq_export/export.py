"""Export a PARQ checkpoint to a model folder: backbone.onnx, layer.onnx and model.json.

The folder is written next to its destination under a temporary name, checked against the torch
model, and only then renamed into place, so a failed export leaves nothing behind.
"""
from __future__ import annotations

import contextlib
import copy
import datetime
import hashlib
import io
import json
import logging
import os
import pathlib
import tempfile
import warnings
from dataclasses import dataclass

import numpy as np
import onnx
import onnxscript.optimizer
import torch

from parq_runtime import __version__, files
from parq_runtime.model_card import level_sizes
from parq_runtime.errors import ParqError
from parq_runtime.model_card import CARD_FORMAT, CARD_VERSION, METADATA_KEY

from . import checkpoint as ckpt
from . import verify
from . import factored
from .graphs import (BACKBONE_GRAPH_OUTPUTS, BACKBONE_INPUTS, BACKBONE_OUTPUTS, CACHED_LEVELS,
                     CACHED_OPERANDS, FACTOR_NAMES, LAYER_INPUTS, LAYER_OUTPUTS, BackboneGraph,
                     CachedOperands, LayerGraph, add_operands_branch, join_layer_forms)
from .model import PARQ

DEFAULT_OPSET = 18
MAX_VIEWS = 9
MAX_QUERIES = 1024
# the card's words for image.filter (parq_runtime.preprocess)
RESIZE_TEXT = {
    "pillow-bilinear": "PIL.Image.resize BILINEAR (antialiased when shrinking); 1296x968 "
                       "frames padded 2 px top and bottom first",
    "point": "point samples: pixel (round(u * W / w), round(v * H / h)); 1296x968 frames "
             "padded 2 px top and bottom first",
}


@dataclass
class ExportResult:
    out_dir: pathlib.Path
    card: dict
    report: dict  # verification: {name: (max abs diff, tolerance)}


def _quiet_export(*args, **kwargs):
    """torch.onnx.export without its progress chatter (errors still raise)."""
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        return torch.onnx.export(*args, **kwargs)


def fold_weights(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Fold computations on weights into constants (the slices of the attention projections,
    the per-channel scale of frozen batch norms ...), so none of them runs per call, and drop
    the initializers left unused (the cross-attention key/value weights of the layer graph).
    The size limits are raised above torch's defaults because the folded tensors are up to
    C x C."""
    return onnxscript.optimizer.optimize(proto, num_iterations=3,
                                         input_size_limit=1 << 26, output_size_limit=1 << 26)


def _factor_examples(model: PARQ, views: int) -> list:
    """Zero tensors shaped like backbone.onnx's factor outputs for ``views`` views."""
    c = model.config
    sizes = level_sizes(c.feature_size)
    (h, w) = sizes[0]
    return ([torch.zeros(views, hl, wl, c.fpn_channels) for hl, wl in sizes]
            + [torch.zeros(views, h, w, c.feature_dim)])


def export_backbone(model: PARQ, opset: int) -> onnx.ModelProto:
    """backbone.onnx without its keys-and-values branch (``add_operands_branch``)."""
    c = model.config
    w, h = c.image_size
    example = (torch.zeros(2, h, w, 3, dtype=torch.uint8), *_factor_examples(model, 1)[:4],
               torch.ones(3, 4), torch.eye(4).repeat(3, 1, 1))
    new = torch.export.Dim("new_views", min=0, max=MAX_VIEWS)
    old = torch.export.Dim("cached_views", min=0, max=MAX_VIEWS)
    auto = torch.export.Dim.AUTO
    program = _quiet_export(
        BackboneGraph(model).eval(), example, dynamo=True, opset_version=opset,
        input_names=list(BACKBONE_INPUTS), output_names=list(BACKBONE_OUTPUTS),
        dynamic_shapes={"images": {0: new}, **{n: {0: old} for n in CACHED_LEVELS},
                        "camera": {0: auto}, "T_local_camera": {0: auto}},
        optimize=True, verify=False)
    return fold_weights(program.model_proto)


def export_cached_operands(model: PARQ, opset: int) -> onnx.ModelProto:
    views = torch.export.Dim("views", min=1, max=MAX_VIEWS)
    program = _quiet_export(
        CachedOperands(model).eval(), tuple(_factor_examples(model, 3)), dynamo=True,
        opset_version=opset, input_names=list(FACTOR_NAMES),
        output_names=list(CACHED_OPERANDS),
        dynamic_shapes={n: {0: views} for n in FACTOR_NAMES}, optimize=True, verify=False)
    return fold_weights(program.model_proto)


def export_layer(model: PARQ, opset: int) -> onnx.ModelProto:
    """layer.onnx: both forms of the layer, joined under If(key_value)."""
    c = model.config
    C, H = c.feature_dim, c.heads
    S = 3 * c.feature_size[0] * c.feature_size[1]
    K = c.num_queries
    queries = torch.export.Dim("queries", min=1, max=MAX_QUERIES)
    tokens = torch.export.Dim("tokens", min=1)
    views = torch.export.Dim("views", min=1, max=MAX_VIEWS)
    example = (torch.zeros(K, C), torch.zeros(K, C), torch.ones(K, 1), torch.full((K, 3), 0.5),
               torch.zeros(H, S, C // H), torch.zeros(H, S, C // H),
               *_factor_examples(model, 3))
    dynamic = {"query_features": {0: queries}, "query_ray_hidden": {0: queries},
               "query_weight": {0: queries}, "reference_points": {0: queries},
               "attention_keys": {1: tokens}, "attention_values": {1: tokens},
               **{n: {0: views} for n in FACTOR_NAMES}}
    forms = {}
    for form in ("cached", "folded"):
        program = _quiet_export(
            LayerGraph(model, form).eval(), example, dynamo=True, opset_version=opset,
            input_names=list(LAYER_INPUTS), output_names=list(LAYER_OUTPUTS),
            dynamic_shapes=dynamic, optimize=True, verify=False)
        forms[form] = fold_weights(program.model_proto)
    return join_layer_forms(forms["cached"], forms["folded"], model)


def build_card(model: PARQ, checkpoint: ckpt.Checkpoint, source: pathlib.Path,
               opset: int) -> dict:
    """Everything the runtime needs, and where the model came from."""
    c = model.config
    fw, fh = c.feature_size
    return {
        "format": CARD_FORMAT,
        "format_version": CARD_VERSION,
        "package_version": __version__,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "opset": opset,
        "checkpoint": {"file": source.name, "sha256": checkpoint.sha256,
                       "layout": checkpoint.layout, "defaulted_fields": checkpoint.defaulted},
        "config": c.to_dict(),
        "classes": list(c.classes),
        "no_object_label": len(c.classes),
        "mean_sizes": [list(map(float, m)) for m in c.mean_sizes],
        "image": {"width": c.image_size[0], "height": c.image_size[1], "channels": "RGB",
                  "dtype": "uint8", "layout": "NHWC",
                  "filter": c.image_filter, "resize": RESIZE_TEXT[c.image_filter],
                  "normalisation": {"scale": 1 / 255, "mean": list(c.pixel_mean),
                                    "std": list(c.pixel_std), "inside_graph": True}},
        "feature": {"stride": c.feature_stride, "width": fw, "height": fh,
                    "channels": c.feature_dim,
                    "camera": "f * s, c' = (c + 0.5) * s - 0.5 with s = 1 / stride"},
        "rays": {"samples": c.ray_samples, "depth": list(c.ray_depth),
                 "scale": list(c.ray_scale)},
        "decoder": {"scale": list(c.decoder_scale), "heads": c.heads,
                    "head_dim": c.feature_dim // c.heads, "iterations": c.iterations,
                    "sampling": "bilinear, align_corners=True, zero padding, summed over all "
                                "views, divided by the number of views where the point is "
                                "valid (z > 1e-3 and inside [0, w-1] x [0, h-1])"},
        "reference_points": model.initial_reference_points().detach().double().tolist(),
        "query_order": [int(i) for i in c.query_order],
        "postprocess": {"score_threshold": c.score_threshold, "nms_iou": c.nms_iou,
                        "eval_region": list(c.eval_region), "fusion": c.fusion,
                        "min_support": c.min_support, "ray_ratio": c.ray_ratio,
                        "scene_nms": c.scene_nms,
                        "floor_classes": list(c.floor_classes),
                        "floor_weight": c.floor_weight, "labels": c.labels,
                        "match_iou": c.match_iou, "phase_support": c.phase_support},
        "snippets": {"gap": c.snippet_gap},
        "run": {"iters": c.run_iters, "queries": c.run_queries, "mirror": c.run_mirror,
                "phases": c.run_phases},
        "limits": {"max_views": MAX_VIEWS, "max_queries": MAX_QUERIES},
        "graphs": {
            "backbone": {"file": "backbone.onnx", "inputs": list(BACKBONE_INPUTS) + ["key_value"],
                         "outputs": list(BACKBONE_GRAPH_OUTPUTS)},
            "layer": {"file": "layer.onnx", "inputs": list(LAYER_INPUTS) + ["key_value"],
                      "outputs": list(LAYER_OUTPUTS)},
        },
        "extra": dict(c.extra),
    }


def _finish_graph(proto: onnx.ModelProto, card: dict, role: str, doc: str) -> onnx.ModelProto:
    del proto.metadata_props[:]
    entries = {METADATA_KEY: json.dumps(card, sort_keys=True), "parq.graph": role,
               "parq.package_version": __version__,
               "parq.checkpoint_sha256": card["checkpoint"]["sha256"]}
    for k, v in entries.items():
        proto.metadata_props.add(key=k, value=v)
    proto.producer_name = "parq-onnx"
    proto.producer_version = __version__
    proto.doc_string = doc
    proto.graph.name = f"parq_{role}"
    onnx.checker.check_model(proto, full_check=False)
    return proto


def quantize_int8(model: PARQ, base: onnx.ModelProto, cached_operands: onnx.ModelProto,
                  card: dict, folder: pathlib.Path, calibration, log) -> dict:
    """Replace folder/backbone.onnx by its int8 version; returns the card's record of it.
    The quantizer works on the graph before the operands branch is added (it cannot follow
    names into If subgraphs), then the branch is added to its output."""
    from . import quantize

    with tempfile.TemporaryDirectory() as tmp:
        scenes = calibration
        if scenes is None:
            scenes = quantize.generate_calibration(pathlib.Path(tmp) / "calibration",
                                                   model.config.image_size)
        feeds = quantize.calibration_feeds(scenes, model.config)
        fp32 = pathlib.Path(tmp) / "backbone_fp32.onnx"
        onnx.save(base, fp32)
        int8 = pathlib.Path(tmp) / "backbone_int8.onnx"
        quantize.quantize_backbone(fp32, int8, [{k: v for k, v in f.items() if k != "key_value"}
                                                for f in feeds])
        proto = add_operands_branch(onnx.load(int8), cached_operands, model,
                                    card["opset"])
        onnx.save(_finish_graph(proto, card, "backbone",
                                "PARQ backbone, int8 convolutions (QDQ, per-channel)"),
                  folder / "backbone.onnx")
    errors = verify.quantization_error(folder / "backbone.onnx", feeds[:4], model)
    log(f"  int8 backbone: memory max abs diff {errors['memory']:.3g} vs fp32 torch "
        f"(relative {errors['memory_relative']:.3g})")
    return {"backbone": "int8 weights (per channel, 7-bit range) and uint8 activations, QDQ, "
                        "convolutions only", "calibration_snippets": len(feeds),
            "calibration_scenes": str(calibration) if calibration else
            "{scenes} parq-synth scenes, seed {seed}, {frames} frames".format(
                **quantize.CALIBRATION), **errors}


def _file_sha256(path) -> str:
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


# What parq-export writes into a model folder: --force replaces a folder holding only these.
MODEL_FILES = ("backbone.onnx", "layer.onnx", "model.json")


def check_replaceable(out_dir: pathlib.Path) -> None:
    """ParqError unless ``out_dir`` is a model folder that --force may replace whole: a
    folder holding nothing but an export's files (a file, or a folder with anything else in
    it, such as the checkpoint itself, is never deleted)."""
    if not out_dir.is_dir():
        raise ParqError(f"{out_dir}: is a file, not a model folder (--force replaces only "
                        "a model folder)")
    others = sorted(p.name for p in out_dir.iterdir() if p.name not in MODEL_FILES)
    if others:
        shown = ", ".join(others[:3]) + (f" and {len(others) - 3} more" if len(others) > 3
                                         else "")
        raise ParqError(f"{out_dir}: holds files an export does not write ({shown}); "
                        "--force replaces only a model folder, choose another -o")


def export(checkpoint_path, out_dir, opset: int = DEFAULT_OPSET, check: bool = True,
           overwrite: bool = False, log=print, quantize: str | None = None,
           calibration=None) -> ExportResult:
    """Export ``checkpoint_path`` to ``out_dir``; raises ParqError on bad input or a failed
    check (then nothing is written).

    quantize="int8": after the fp32 graphs pass the check, backbone.onnx's convolutions are
    quantized (see parq_export.quantize), calibrated on the generated scenes in ``calibration``
    (default: quantize.CALIBRATION, scenes generated here)."""
    if quantize not in (None, "int8"):
        raise ParqError(f"--quantize {quantize}: only int8 is supported")
    source = pathlib.Path(checkpoint_path)
    out_dir = pathlib.Path(out_dir)
    if opset not in (17, 18):
        raise ParqError(f"--opset {opset}: use 17 or 18 (onnxruntime's CUDA provider has no "
                        "GridSample-20, and the graphs need LayerNormalization-17)")
    if quantize is None and calibration is not None:
        raise ParqError(f"--calibration {calibration}: only used with --quantize int8")
    if out_dir.exists() and not overwrite:
        raise ParqError(f"{out_dir}: already exists (use --force to replace it)")
    if out_dir.exists():
        check_replaceable(out_dir)
    parent = out_dir.absolute().parent
    if not parent.is_dir():
        raise ParqError(f"{parent}: output folder's parent does not exist")
    if not os.access(parent, os.W_OK):
        raise ParqError(f"{parent}: not writable")
    checkpoint = ckpt.load(source)
    log(f"loaded {source} ({checkpoint.layout} layout, ResNet{checkpoint.config.resnet_depth}, "
        f"{checkpoint.config.num_queries} queries)")
    if checkpoint.defaulted:
        log("not recorded in the checkpoint, taken from the authors' eval.yaml: "
            + ", ".join(checkpoint.defaulted))
    model = checkpoint.model()
    card = build_card(model, checkpoint, source, opset)
    with files.atomic_folder(out_dir, "the model folder") as tmp:
        with torch.no_grad():
            backbone_base = export_backbone(model, opset)
            cached_operands = export_cached_operands(model, opset)
            backbone = add_operands_branch(copy.deepcopy(backbone_base), cached_operands,
                                           model, opset)
            layer = export_layer(model, opset)
        onnx.save(_finish_graph(backbone, card, "backbone",
                                "PARQ backbone: images + cameras of one snippet -> memory and "
                                "attention operands"), tmp / "backbone.onnx")
        onnx.save(_finish_graph(layer, card, "layer",
                                "One recurrent PARQ layer: query content + reference points + "
                                "attention operands -> box parameters"), tmp / "layer.onnx")
        report = {}
        if check:
            report = verify.check(model, tmp / "backbone.onnx", tmp / "layer.onnx")
            for name, (diff, tol) in sorted(report.items()):
                log(f"  check {name:42s} max abs diff {diff:.2e} (tolerance {tol:.1e})")
            bad = verify.failed(report)
            if bad:
                raise ParqError(f"export check failed for {', '.join(bad)}: the graphs do not "
                                "reproduce the torch model (nothing was written)")
        card["verification"] = {k: {"max_abs_diff": d, "tolerance": t}
                                for k, (d, t) in sorted(report.items())}
        if quantize:
            card["quantization"] = quantize_int8(model, backbone_base, cached_operands, card,
                                                 tmp, calibration, log)
        for role in ("backbone", "layer"):
            card["graphs"][role]["sha256"] = _file_sha256(tmp / card["graphs"][role]["file"])
        (tmp / "model.json").write_text(json.dumps(card, indent=1) + "\n")
    return ExportResult(out_dir, card, report)
