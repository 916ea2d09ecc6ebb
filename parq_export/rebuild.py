"""A torch checkpoint from an exported model folder: the weights read back out of its graphs.

A model folder is what gets shipped (the demo's training checkpoint is not in the repository),
yet continuing training, or exporting again with a newer exporter, needs the torch model.  The
graphs hold every parameter, but the export moved them: transposed, sliced out of the packed
attention projections, reordered (the ray MLP's input columns), and each frozen batch norm
reduced to its scale weight / sqrt(var + eps) and shift.

So the map is learned rather than written down.  A *probe* model of the folder's configuration
is exported the same way, every parameter element set to a distinct value (1 + 4 (k + 1) /
2^23 for a seeded permutation k: exact in float32, 4 ulps apart, never 1), its batch-norm
statistics to mean 0 and variance 4 - eps (so that a norm's scale is its weight halved, in
[0.5, 1), where no probe value lies).  Each constant element of the probe's graphs is looked
up among those values, as is or doubled (a batch norm's scale).  A constant whose elements are
all found is a rearrangement of parameters, and the folder's constant of the same name gives
those parameters' values; one made from several, such as a product of two weights, is skipped.
What the graphs do not hold comes from elsewhere: the learned reference points from the card
(logits of its normalised points), each batch norm as weight = scale, bias = shift, mean 0,
variance 1 (the same function), and the cross-attention's key bias as 0 (it adds one constant
to each query's scores, which softmax removes, so the export drops it).

Older exports kept some raw parameters under their own names where the current exporter
rearranges them (the demo's ray MLP input weight): a probe constant missing from the folder is
then taken from the folder's constant named after the parameter.

The result is checked as an export is: ``verify.check`` runs the rebuilt model against the
folder's own graphs, and any difference past the export tolerances is an error.  On the demo
(``models/parq-demo``, 17 s) the largest differences are 1.6e-5 on the backbone's outputs and
6.7e-6 on the layer's, as in the demo's own export check; exported again, the rebuilt model
gives the demo's detections and its F1 on 10 validation scenes exactly.  The configuration is
the card's own ``config`` with the post-processing, query ranking, snippet gap and run setting
taken from the rest of the card (:func:`card_config`): a tuning rewrites those there, and the
demo's ``config`` still holds an early tuning's (score 0.7, ``mean`` fusion, support 2, no
mirror runs, scene NMS or floor prior), which the demo rebuilt and exported again got before.

    python -m parq_export.rebuild models/parq-demo -o work/demo-rebuilt.pt
"""
from __future__ import annotations

import argparse
import copy
import pathlib
import sys

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from parq_runtime import model_card
from parq_runtime.errors import ParqError

from . import checkpoint, verify
from .config import PARQConfig
from .export import DEFAULT_OPSET, export_backbone, export_cached_operands, export_layer
from .graphs import add_operands_branch
from .model import PARQ

SPACING = 4                      # ulps between probe values in [1, 2)
ULP = 2.0 ** -23
EPS = 1e-5                       # FrozenBatchNorm2d's


def constants(proto: onnx.ModelProto) -> dict:
    """{name: array} of a graph's initializers and Constant nodes, those of If branches named
    ``then/...`` or ``else/...`` (nested branches by their path)."""
    out = {}

    def walk(graph, prefix):
        for init in graph.initializer:
            out.setdefault(prefix + init.name, numpy_helper.to_array(init))
        for node in graph.node:
            for attribute in node.attribute:
                if node.op_type == "Constant" and attribute.name == "value":
                    out.setdefault(prefix + node.output[0], numpy_helper.to_array(attribute.t))
                if attribute.type == onnx.AttributeProto.GRAPH:
                    walk(attribute.g, prefix + attribute.name + "/")
    walk(proto.graph, "")
    return out


def correspondence(mine: onnx.ModelProto, theirs: onnx.ModelProto, my_constants: dict,
                   their_constants: dict) -> dict:
    """{constant of ``mine``: the constant of ``theirs`` that the same input of the same node
    reads} (the constants being each graph's :func:`constants`), in every graph scope whose
    nodes are the same ops in the same order (the same exporter).  Names alone do not do: an
    export merges equal constants (a fresh model's batch norms are all alike), and the
    probe's, all distinct, are not merged."""
    def scopes(proto, names):
        out = {}

        def walk(graph, prefix):
            ops, reads = [], {}
            for i, node in enumerate(graph.node):
                ops.append(node.op_type)
                for j, name in enumerate(node.input):
                    for scoped in (prefix + name, name):
                        if scoped in names:
                            reads[i, j] = scoped
                            break
                for attribute in node.attribute:
                    if attribute.type == onnx.AttributeProto.GRAPH:
                        walk(attribute.g, prefix + attribute.name + "/")
            out[prefix] = (ops, reads)
        walk(proto.graph, "")
        return out
    ours, other = scopes(mine, my_constants), scopes(theirs, their_constants)
    pairs = {}
    for prefix, (ops, reads) in ours.items():
        if prefix in other and other[prefix][0] == ops:
            for slot, name in reads.items():
                if slot in other[prefix][1]:
                    pairs.setdefault(name, other[prefix][1][slot])
    return pairs


def trainable_state(model: PARQ) -> list:
    """Names of the state entries the graphs carry: everything but batch-norm statistics and
    the buffers the configuration decides (pixel statistics, sample grids)."""
    derived = {name for name, _ in model.named_buffers()
               if not name.endswith((".weight", ".bias"))}
    return [k for k in model.state_dict() if k not in derived and k != "refpoint.weight"]


def probe_model(config: PARQConfig, seed: int = 0) -> tuple:
    """(model, names, offsets): the probe (module doc): state elements 1 + SPACING (k + 1)
    ULP, batch-norm statistics mean 0 and variance 4 - eps; ``offsets[name]`` holds the k of
    that entry's elements in row-major order."""
    model = PARQ(config)
    state = model.state_dict()
    names = trainable_state(model)
    total = sum(state[k].numel() for k in names)
    if total * SPACING >= 2 ** 23:
        raise ParqError(f"the model has {total} parameters: too many for distinct probe values")
    k = np.random.default_rng(seed).permutation(total)
    offsets, start = {}, 0
    with torch.no_grad():
        for name in names:
            n = state[name].numel()
            values = 1.0 + SPACING * (k[start:start + n] + 1).astype(np.float64) * ULP
            state[name].copy_(torch.from_numpy(values.astype(np.float32)).view_as(state[name]))
            offsets[name] = k[start:start + n]
            start += n
        for name, buffer in model.named_buffers():
            if name.endswith("running_mean"):
                buffer.zero_()
            elif name.endswith("running_var"):
                buffer.fill_(4.0 - EPS)      # scale = weight / 2: out of the grid, exactly
    return model, names, offsets


def export_graphs(model: PARQ, opset: int = DEFAULT_OPSET) -> dict:
    """{role: ModelProto} as parq_export.export writes them (no check, nothing on disk)."""
    with torch.no_grad():
        backbone = add_operands_branch(export_backbone(model, opset),
                                       export_cached_operands(model, opset), model, opset)
        return {"backbone": backbone, "layer": export_layer(model, opset)}


def locate(values: np.ndarray, total: int) -> tuple:
    """(k (M,) int, -1 where not a probe value; scaled (M,) bool: found halved, a batch
    norm's scale in the probe) for float32 constant elements."""
    v = values.astype(np.float64).ravel()

    def grid(x):
        k = np.rint((x - 1.0) / (SPACING * ULP)) - 1
        exact = np.abs(1.0 + (k + 1) * SPACING * ULP - x) <= 1.5 * ULP
        return k.astype(np.int64), exact & (k >= 0) & (k < total)
    k, hit = grid(v)
    k2, hit2 = grid(v * 2.0)
    scaled = ~hit & hit2
    return np.where(hit, k, np.where(scaled, k2, -1)), scaled


def card_config(card) -> PARQConfig:
    """The folder's configuration: the card's ``config`` (the exporter's PARQConfig as it
    was), with what the runtime reads from elsewhere in the card taken from there, since a
    tuning rewrites those (parq_export.card_rewrite) and older cards' ``config`` predates
    some: the post-processing, the query ranking, the snippet gap, the resize filter and the
    run setting.  So the rebuilt checkpoint exports to the card it came from."""
    order = card.query_order
    return PARQConfig.from_dict(card.raw["config"]).replace(
        score_threshold=card.score_threshold, nms_iou=card.nms_iou,
        eval_region=card.eval_region, fusion=card.fusion, min_support=card.min_support,
        ray_ratio=card.ray_ratio, scene_nms=card.scene_nms, floor_classes=card.floor_classes,
        floor_weight=card.floor_weight, labels=card.labels, match_iou=card.match_iou,
        query_order=() if order is None else tuple(int(i) for i in order),
        snippet_gap=card.snippet_gap, image_filter=card.image_filter,
        run_iters=card.run_iters, run_queries=card.run_queries, run_mirror=card.run_mirror,
        run_phases=card.run_phases, phase_support=card.phase_support)


def rebuild(folder, opset: int = DEFAULT_OPSET, log=print) -> PARQ:
    """The torch PARQ whose export is the model folder ``folder``; raises ParqError when a
    parameter is not found in its graphs or the rebuilt model does not reproduce them."""
    folder = pathlib.Path(folder)
    card = model_card.load(folder)
    config = card_config(card)
    probe, names, offsets = probe_model(config)
    total = sum(len(o) for o in offsets.values())
    entry, position = np.empty(total, np.int64), np.empty(total, np.int64)
    for e, name in enumerate(names):
        entry[offsets[name]] = e
        position[offsets[name]] = np.arange(len(offsets[name]))
    state = {k: v.clone() for k, v in PARQ(config).state_dict().items()}
    flat = {name: np.full(state[name].numel(), np.nan) for name in names}
    for role, proto in export_graphs(probe, opset).items():
        path = folder / card.raw["graphs"][role]["file"]
        target = onnx.load(str(path))
        ours, theirs = constants(proto), constants(target)
        same = correspondence(proto, target, ours, theirs)
        for cname, mine in ours.items():
            if mine.dtype != np.float32 or mine.size == 0:
                continue
            ks, scaled = locate(mine, total)
            if mine.size < 2 or (ks < 0).any():
                continue                      # not (only) parameters: a product, a config value
            used = sorted({names[e] for e in entry[ks]})
            tname = same.get(cname, cname)
            if tname not in theirs:          # an older export kept the raw parameter
                raw = [r for r in (f"model.{used[0]}", used[0]) if r in theirs]
                if len(used) != 1 or not raw or theirs[raw[0]].size != mine.size:
                    raise ParqError(f"{path}: no constant {cname} (the export of "
                                    f"{', '.join(used)}), nor that parameter by name")
                flat[used[0]][:] = theirs[raw[0]].astype(np.float64).ravel()
                continue
            value = theirs[tname].astype(np.float64).ravel()
            if value.size != ks.size:
                raise ParqError(f"{path}: constant {cname} has {value.size} elements, the "
                                f"exporter makes {ks.size}: another configuration?")
            value = np.where(scaled, value * np.sqrt(1.0 + EPS), value)
            for e in np.unique(entry[ks]):
                rows = entry[ks] == e
                dest = flat[names[e]]
                before = dest[position[ks[rows]]]
                known = ~np.isnan(before)
                if not np.allclose(before[known], value[rows][known], rtol=1e-5, atol=1e-7):
                    raise ParqError(f"{path}: constant {cname} disagrees with another "
                                    f"export of {names[e]}")
                dest[position[ks[rows]]] = value[rows]
    fill_unexported(flat, config)
    missing = [name for name, v in flat.items() if np.isnan(v).any()]
    if missing:
        raise ParqError(f"{folder}: the graphs do not hold {', '.join(missing[:4])}"
                        + (f" and {len(missing) - 4} more" if len(missing) > 4 else ""))
    for name, v in flat.items():
        state[name] = torch.from_numpy(v.astype(np.float32)).view_as(state[name])
    u = torch.as_tensor(card.reference_points, dtype=torch.float64)
    state["refpoint.weight"] = torch.log(u / (1 - u)).float()
    model = PARQ(config)
    model.load_state_dict(state)
    model.eval()
    report = verify.check(model, folder / card.raw["graphs"]["backbone"]["file"],
                          folder / card.raw["graphs"]["layer"]["file"])
    bad = verify.failed(report)
    if bad:
        raise ParqError(f"{folder}: the rebuilt model does not reproduce the graphs "
                        f"({', '.join(bad)})")
    log("rebuilt; largest differences from the folder's graphs: "
        + ", ".join(f"{k} {d:.1e}" for k, (d, _) in sorted(report.items(),
                                                          key=lambda kv: -kv[1][0])[:3]))
    return model


def fill_unexported(flat: dict, config: PARQConfig) -> None:
    """The parameter elements no graph holds: the cross-attention's key bias, which the
    exporter drops (softmax removes a per-query constant), is 0."""
    name = "layer.decoder.multihead_attn.in_proj_bias"
    C = config.feature_dim
    if name in flat:
        key = flat[name][C:2 * C]
        key[np.isnan(key)] = 0.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m parq_export.rebuild",
                                description="Read a torch checkpoint back out of a model "
                                            "folder's graphs (checked against them).")
    p.add_argument("folder", type=pathlib.Path, help="model folder written by parq-export")
    p.add_argument("-o", "--output", type=pathlib.Path, required=True,
                   help="checkpoint to write (.pt, this package's format)")
    p.add_argument("--force", action="store_true", help="replace OUTPUT if it exists")
    args = p.parse_args(argv)
    try:
        if args.output.exists() and not args.force:
            raise ParqError(f"{args.output}: already exists (use --force to replace it)")
        model = rebuild(args.folder, log=lambda m: print(m, file=sys.stderr))
        model.config = model.config.replace(extra=dict(
            copy.deepcopy(model.config.extra or {}), rebuilt_from=str(args.folder)))
        checkpoint.save(args.output, model, {"rebuilt_from": str(args.folder)})
    except ParqError as e:
        print(f"rebuild: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
