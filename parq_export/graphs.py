"""The two exported graphs as torch modules.

Neither graph forms the cross-attention's memory: they pass it in factored form, the FPN levels
at their own resolution and the ray MLP's hidden layer (see ``parq_export.factored``).

``backbone.onnx`` (one snippet, everything the loop needs):
  inputs  images (Nn, H, W, 3) uint8 RGB at the network resolution, frames not encoded yet;
          cached_level_0..3 (Nc, h_l, w_l, F) float32: ``level_l`` of frames encoded by an
          earlier call (streaming; Nc may be 0);
          camera (N, 4) float32 (fx, fy, cx, cy) at feature resolution, N = Nc + Nn, in the
          order [cached frames..., new frames...];
          T_local_camera (N, 4, 4) float32;
          key_value (bool scalar): true projects the attention keys and values here, once per
          snippet (the cached form); false leaves them empty (the folded form).
  outputs level_0..3 (N, h_l, w_l, F): FPN levels P2..P5 of every view, cached ones first;
          ray_hidden (N, h, w, C): the ray MLP's hidden layer;
          memory (N, h, w, C) in the cached form, formed there to project the keys and
          values and returned for the loop to sample, (0, 0, 0, C) in the folded form;
          attention_keys, attention_values: (H, S, d) in the cached form, (0, 0, d) in the
          folded form.

``layer.onnx`` (one PARQ iteration, K queries):
  inputs  query_features (K, C), query_ray_hidden (K, C), query_weight (K, 1): the query
          content's factors (``parq_runtime.loop.sample_factors``) in the folded form; the
          cached form reads query_features only, the sampled memory
          (``parq_runtime.loop.sample_memory``); reference_points (K, 3)
          normalised; attention_keys, attention_values; level_0..3, ray_hidden (the folded
          form reads these; the cached form ignores them); key_value (bool scalar): the form;
  outputs center (K, 3), size (K, 3), ortho6d (K, 6), rotation (K, 3, 3), logits (K, C + 1),
          next_reference_points (K, 3).
"""
from __future__ import annotations

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

from parq_runtime.model_card import level_sizes
from parq_runtime.loop import (FACTOR_NAMES, LAYER_OUTPUTS, MEMORY_NAME, OPERAND_NAMES,
                               QUERY_NAMES)

from . import conditional, factored
from .model import PARQ

CACHED_LEVELS = tuple(f"cached_{n}" for n in FACTOR_NAMES[:-1])
BACKBONE_INPUTS = ("images",) + CACHED_LEVELS + ("camera", "T_local_camera")
BACKBONE_OUTPUTS = FACTOR_NAMES
CACHED_OPERANDS = (MEMORY_NAME,) + OPERAND_NAMES
# backbone.onnx's outputs once the cached form's If is merged in: what model.json lists
BACKBONE_GRAPH_OUTPUTS = BACKBONE_OUTPUTS + CACHED_OPERANDS
LAYER_INPUTS = QUERY_NAMES + ("reference_points",) + OPERAND_NAMES + FACTOR_NAMES


class BackboneGraph(nn.Module):
    """Image encoder + the ray MLP's hidden layer for one snippet (the keys and values are
    added in ONNX, see :func:`add_operands_branch`)."""

    def __init__(self, model: PARQ):
        super().__init__()
        self.model = model

    def forward(self, images, cached_level_0, cached_level_1, cached_level_2, cached_level_3,
                camera, T_local_camera):
        x = images.permute(0, 3, 1, 2).to(torch.float32) / 255.0
        new = self.model.backbone.levels(x)
        cached = (cached_level_0, cached_level_1, cached_level_2, cached_level_3)
        levels = [torch.cat([old, p.permute(0, 2, 3, 1)], 0) for old, p in zip(cached, new)]
        return (*levels, self.model.ray_encoder.hidden_coordinate_major(camera, T_local_camera))


class CachedOperands(nn.Module):
    """The cached form's memory (N, h, w, C), formed from the factors, and its keys and
    values (H, S, d) without biases (see ``DecoderLayer.attention_operands``).

    Each is one (S, C) @ (C, C) product, then a transposed copy to (H, S, d).  onnxruntime
    packs a constant 2-D right operand once, at load; the (1, S, C) @ (H, C, d) batched
    product used before packs it at every call.  For the authors' configuration the two
    products and their copies take 205-216 ms on this machine's 2 cores, the batched products
    226-243 ms (``benchmarks/results/latency.md`` has the whole backbone)."""

    def __init__(self, model: PARQ):
        super().__init__()
        self.model = model

    def forward(self, level_0, level_1, level_2, level_3, ray_hidden):
        memory = factored.memory([level_0, level_1, level_2, level_3], ray_hidden,
                                 self.model.ray_encoder.mlp[2])
        W = self.model.layer.decoder.multihead_attn.in_proj_weight
        C = memory.shape[-1]
        H = self.model.config.heads
        tokens = memory.reshape(-1, C)                                       # (S, C)

        def heads(projected):                                                # (S, C) -> (H, S, d)
            return projected.reshape(-1, H, C // H).transpose(0, 1)

        return memory, heads(tokens @ W[C:2 * C].T), heads(tokens @ W[2 * C:].T)


class LayerGraph(nn.Module):
    """One PARQ iteration on one snippet, in one form of the cross-attention: ``cached``
    (attention_keys and attention_values; the content is query_features, the sampled memory)
    or ``folded`` (the factors, and the content from the sampled factors)."""

    def __init__(self, model: PARQ, form: str):
        super().__init__()
        self.layer = model.layer
        self.ray_out = model.ray_encoder.mlp[2]
        self.form = form
        c = model.config
        self.weights = factored.FactoredWeights(self.layer.decoder.multihead_attn, self.ray_out,
                                                c.heads)
        sizes = level_sizes(c.feature_size)
        h, w = sizes[0]
        self.resize = [(factored.resize_matrix(h, hl), factored.resize_matrix(w, wl))
                       for hl, wl in sizes[1:]]
        for i, (rows, cols) in enumerate(self.resize):
            self.register_buffer(f"rows_{i}", rows, persistent=False)
            self.register_buffer(f"cols_{i}", cols, persistent=False)

    def forward(self, query_features, query_ray_hidden, query_weight, reference_points,
                attention_keys, attention_values, level_0, level_1, level_2, level_3,
                ray_hidden):
        decoder = self.layer.decoder
        H = decoder.heads

        def attend(y):
            K, C = y.shape[1:]
            if self.form == "cached":
                d = C // H
                eye = torch.eye(d, dtype=y.dtype).expand(H, d, d)
                value_bias = decoder.multihead_attn.in_proj_bias[2 * C:].reshape(H, 1, d)
                return decoder.cross_attention(y, attention_keys[None], attention_values[None],
                                               eye, eye, value_bias)
            resize = [(getattr(self, f"rows_{i}"), getattr(self, f"cols_{i}"))
                      for i in range(3)]
            ctx = factored.folded_attention(decoder.cross_queries(y)[0],
                                            [level_0, level_1, level_2, level_3], ray_hidden,
                                            self.weights(), resize)
            return decoder.multihead_attn.out_proj(ctx.transpose(0, 1).reshape(1, K, C))

        if self.form == "cached":
            content = query_features
        else:
            content = factored.content(query_features, query_ray_hidden, query_weight,
                                       self.ray_out)
        out = self.layer(content[None], reference_points[None], attend=attend)
        return tuple(out[name][0] for name in LAYER_OUTPUTS)


def empty_operands(model: PARQ, opset: int) -> onnx.ModelProto:
    """The folded form's branch of backbone.onnx: empty memory (0, 0, 0, C), keys and values
    (0, 0, d)."""
    C = model.config.feature_dim
    d = C // model.config.heads
    memory = numpy_helper.from_array(np.zeros((0, 0, 0, C), np.float32), "empty_memory")
    empty = numpy_helper.from_array(np.zeros((0, 0, d), np.float32), "empty")
    graph = helper.make_graph(
        [helper.make_node("Constant", [], ["memory"], value=memory),
         helper.make_node("Constant", [], ["keys"], value=empty),
         helper.make_node("Identity", ["keys"], ["values"])], "folded_operands", [],
        [helper.make_tensor_value_info("memory", TensorProto.FLOAT, [0, 0, 0, C])]
        + [helper.make_tensor_value_info(n, TensorProto.FLOAT, [0, 0, d])
           for n in ("keys", "values")])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])


def operand_infos(model: PARQ) -> list:
    d = model.config.feature_dim // model.config.heads
    return [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["key_heads", "tokens", d])
            for n in OPERAND_NAMES]


def add_operands_branch(backbone: onnx.ModelProto, cached: onnx.ModelProto, model: PARQ,
                        opset: int) -> onnx.ModelProto:
    """Append ``If(key_value)`` to backbone.onnx: the exported :class:`CachedOperands` when
    true, :func:`empty_operands` when false."""
    memory = helper.make_tensor_value_info(MEMORY_NAME, TensorProto.FLOAT,
                                           ["views", "rows", "cols", model.config.feature_dim])
    return conditional.add_if(backbone, "key_value", cached, empty_operands(model, opset),
                              list(CACHED_OPERANDS), [memory] + operand_infos(model))


def join_layer_forms(cached: onnx.ModelProto, folded: onnx.ModelProto,
                     model: PARQ) -> onnx.ModelProto:
    """layer.onnx: both exported forms of :class:`LayerGraph` under ``If(key_value)``, with
    inputs shared (the keys and values may be empty when the folded form runs)."""
    inputs = {i.name: i for i in folded.graph.input}
    inputs.update({i.name: i for i in cached.graph.input})
    infos = [inputs[n] for n in LAYER_INPUTS if n not in OPERAND_NAMES] + operand_infos(model)
    order = {n: i for i, n in enumerate(LAYER_INPUTS)}
    infos.sort(key=lambda i: order[i.name])
    outer = helper.make_model(helper.make_graph([], "parq_layer", infos, []),
                              opset_imports=cached.opset_import, ir_version=cached.ir_version)
    outputs = [o for o in cached.graph.output]
    return conditional.add_if(outer, "key_value", cached, folded, list(LAYER_OUTPUTS), outputs)
