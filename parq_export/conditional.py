"""Join exported graphs under one ONNX ``If``, so a model file holds two exact forms of a
computation and the caller picks one per call with a bool input.

torch.export cannot trace ``torch.cond`` here (it reports aliasing in the branches), so each
form is exported on its own and the two graphs become the branches: their inputs are read from
the enclosing graph by name, their own tensors are renamed under a branch prefix, and their
weights move to the enclosing graph, stored once when both branches hold the same bytes.
"""
from __future__ import annotations

import hashlib

import onnx
from onnx import TensorProto, helper, numpy_helper


def _branch(proto: onnx.ModelProto, prefix: str, outer: onnx.GraphProto, stored: dict,
            outputs: list) -> onnx.GraphProto:
    """The graph of ``proto`` as an If branch whose outputs are ``outputs`` (in the order of
    the graph's outputs); weights go to ``outer`` (``stored``: digest -> name there)."""
    g = proto.graph
    free = {i.name for i in g.input}
    rename = {}
    for init in g.initializer:
        array = numpy_helper.to_array(init)
        digest = hashlib.sha256(f"{array.dtype}{array.shape}".encode()
                                + array.tobytes()).hexdigest()
        if digest not in stored:
            copy = onnx.TensorProto()
            copy.CopyFrom(init)
            copy.name = f"{prefix}{init.name}"
            outer.initializer.append(copy)
            stored[digest] = copy.name
        rename[init.name] = stored[digest]

    def name(n: str) -> str:
        if n == "" or n in free:
            return n
        return rename.setdefault(n, prefix + n)

    # An output produced by a node of the branch is written there under its outer name.  An
    # Identity would do the same, but onnxruntime keeps it (a copy of the whole tensor, 28 ms
    # for the authors' memory) when the branch also reads the tensor, as the cached form reads
    # the memory it returns.
    produced = {o for node in g.node for o in node.output}
    for out, target in zip(g.output, outputs):
        if out.name in produced and out.name not in rename:
            rename[out.name] = prefix + "out/" + target

    nodes = []
    for node in g.node:
        if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS)
               for a in node.attribute):
            raise ValueError(f"{node.name}: nested subgraphs are not supported")
        new = onnx.NodeProto()
        new.CopyFrom(node)
        new.name = prefix + node.name
        new.input[:] = [name(n) for n in node.input]
        new.output[:] = [name(n) for n in node.output]
        nodes.append(new)
    outs = []
    for out, target in zip(g.output, outputs):
        if name(out.name) != prefix + "out/" + target:
            # An If branch's outputs must be produced inside it: pass-throughs get an Identity.
            nodes.append(helper.make_node("Identity", [name(out.name)],
                                          [prefix + "out/" + target]))
        info = onnx.ValueInfoProto()
        info.CopyFrom(out)
        info.name = prefix + "out/" + target
        outs.append(info)
    return helper.make_graph(nodes, prefix.rstrip("/"), [], outs)


def add_if(outer: onnx.ModelProto, condition: str, then_proto: onnx.ModelProto,
           else_proto: onnx.ModelProto, outputs: list, output_infos: list) -> onnx.ModelProto:
    """Append ``If(condition)`` to ``outer``: ``then_proto`` runs when it is true.  Both
    graphs' inputs must be names visible in ``outer`` (its inputs or node outputs); their
    outputs, in order, become ``outputs`` (added to outer's outputs with ``output_infos``).
    ``condition`` is added as a bool scalar input if outer lacks it."""
    g = outer.graph
    if condition not in {i.name for i in g.input}:
        g.input.append(helper.make_tensor_value_info(condition, TensorProto.BOOL, []))
    stored: dict = {}
    then_graph = _branch(then_proto, "then/", g, stored, outputs)
    else_graph = _branch(else_proto, "else/", g, stored, outputs)
    g.node.append(helper.make_node("If", [condition], list(outputs), name=f"if_{condition}",
                                   then_branch=then_graph, else_branch=else_graph))
    g.output.extend(output_infos)
    for proto in (then_proto, else_proto):
        known = {f.name for f in outer.functions}
        outer.functions.extend(f for f in proto.functions if f.name not in known)
    return outer
