"""The two exported graphs as torch modules, and the per-snippet attention operands branch.

``backbone.onnx`` (one snippet, everything the loop needs):
  inputs  images (Nn, H, W, 3) uint8 RGB at the network resolution, frames not encoded yet;
          cached_features (Nc, C, h, w) float32, ``features`` of frames encoded by an earlier
          call (streaming; Nc may be 0);
          camera (N, 4) float32 (fx, fy, cx, cy) at feature resolution, N = Nc + Nn, in the
          order [cached frames..., new frames...];
          T_local_camera (N, 4, 4) float32;
          key_value (bool scalar): true gives the cached form of the attention operands (keys
          and values projected here, once per snippet), false the folded form (no projection).
  outputs features (Nn, C, h, w): concatenated FPN levels of the new frames;
          memory (N, h, w, C): features + ray encoding, the tokens of the cross-attention;
          attention_keys, attention_values: (H, S, d) in the cached form; empty (0, 0, C) in
          the folded form, where the memory itself, as (1, S, C), takes their place;
          key_map (H, d, Dk), value_map (H, Dv, d), value_bias (H, 1, d): see
          ``parq_export.layer``.

``layer.onnx`` (one PARQ iteration, K queries):
  inputs  query_content (K, C), reference_points (K, 3) normalised, attention_keys (Hk, S, Dk),
          attention_values (Hk, S, Dv), key_map, value_map, value_bias;
  outputs center (K, 3), size (K, 3), ortho6d (K, 6), rotation (K, 3, 3), logits (K, C + 1),
          next_reference_points (K, 3).
"""
from __future__ import annotations

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

from parq_runtime.loop import LAYER_OUTPUTS, OPERAND_NAMES

from .model import PARQ

BACKBONE_INPUTS = ("images", "cached_features", "camera", "T_local_camera")
BACKBONE_OUTPUTS = ("features", "memory")
LAYER_INPUTS = ("query_content", "reference_points") + OPERAND_NAMES


class BackboneGraph(nn.Module):
    """Image encoder + ray encoding for one snippet (the operands branch is added in ONNX)."""

    def __init__(self, model: PARQ):
        super().__init__()
        self.model = model

    def forward(self, images, cached_features, camera, T_local_camera):
        x = images.permute(0, 3, 1, 2).to(torch.float32) / 255.0
        features = self.model.backbone(x)
        every = torch.cat([cached_features, features], 0)
        # No batch axis here: indexing one out (x[0]) would export as a 59 MB Gather copy.
        memory = every.permute(0, 2, 3, 1) + self.model.ray_encoder(camera, T_local_camera)
        return features, memory


class LayerGraph(nn.Module):
    """One PARQ iteration on one snippet."""

    def __init__(self, model: PARQ):
        super().__init__()
        self.layer = model.layer

    def forward(self, query_content, reference_points, attention_keys, attention_values,
                key_map, value_map, value_bias):
        out = self.layer(query_content[None], reference_points[None],
                         operands=(attention_keys[None], attention_values[None], key_map,
                                   value_map, value_bias))
        return tuple(out[name][0] for name in LAYER_OUTPUTS)


def operand_arrays(model: PARQ) -> dict:
    """Cross-attention weights laid out per head: key_weight, value_weight (H, C, d) = W^T of
    each head, key_map (H, d, C) = W_k of each head, key_bias, value_bias (H, 1, d)."""
    attn = model.layer.decoder.multihead_attn
    C = model.config.feature_dim
    H = model.config.heads
    d = C // H
    W = attn.in_proj_weight.detach().numpy().astype(np.float32)
    b = attn.in_proj_bias.detach().numpy().astype(np.float32)
    return {
        "key_weight": np.ascontiguousarray(W[C:2 * C].reshape(H, d, C).transpose(0, 2, 1)),
        "value_weight": np.ascontiguousarray(W[2 * C:].reshape(H, d, C).transpose(0, 2, 1)),
        "key_map": W[C:2 * C].reshape(H, d, C).copy(),
        "key_bias": b[C:2 * C].reshape(H, 1, d).copy(),
        "value_bias": b[2 * C:].reshape(H, 1, d).copy(),
    }


def add_operands_branch(graph_model: onnx.ModelProto, model: PARQ) -> onnx.ModelProto:
    """Append ``If(key_value)`` computing the attention operands from the ``memory`` output.

    Cached branch: keys = memory W_k^T + b_k and values = memory W_v^T + b_v per head, as
    (1, S, C) @ (H, C, d) batched products (no transposes); identity maps, zero value bias.
    Folded branch: empty keys/values, key_map = W_k, value_map = W_v^T, value_bias = b_v.
    """
    C = model.config.feature_dim
    H = model.config.heads
    d = C // H
    w = operand_arrays(model)
    g = graph_model.graph

    def init(name, array):
        return numpy_helper.from_array(np.asarray(array), name)

    shapes = {"keys": ["operand_heads", "tokens", "operand_width"],
              "values": ["operand_heads", "tokens", "operand_width"],
              "key_map": [H, d, "operand_width"], "value_map": [H, "operand_width", d],
              "value_bias": [H, 1, d]}

    def out(name):
        key = name.split("/")[-1].replace("attention_", "")
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, shapes[key])

    g.initializer.extend([init(f"operands/{k}", v) for k, v in w.items()]
                         + [init("operands/tokens_shape", np.array([1, -1, C], np.int64))])
    g.node.append(helper.make_node("Reshape", ["memory", "operands/tokens_shape"],
                                   ["operands/tokens"], name="operands/tokens"))
    cached = helper.make_graph(
        [helper.make_node("MatMul", ["operands/tokens", "operands/key_weight"], ["c/k"]),
         helper.make_node("Add", ["c/k", "operands/key_bias"], ["c/keys"]),
         helper.make_node("MatMul", ["operands/tokens", "operands/value_weight"], ["c/v"]),
         helper.make_node("Add", ["c/v", "operands/value_bias"], ["c/values"]),
         helper.make_node("Identity", ["c/eye"], ["c/key_map"]),
         helper.make_node("Identity", ["c/eye"], ["c/value_map"]),
         helper.make_node("Identity", ["c/zero"], ["c/value_bias"])],
        "cached_operands", [],
        [out(n) for n in ("c/keys", "c/values", "c/key_map", "c/value_map", "c/value_bias")],
        [init("c/eye", np.broadcast_to(np.eye(d, dtype=np.float32), (H, d, d))),
         init("c/zero", np.zeros((H, 1, d), np.float32))])
    folded = helper.make_graph(
        [helper.make_node("Identity", ["f/empty"], ["f/keys"]),
         helper.make_node("Identity", ["f/empty"], ["f/values"]),
         helper.make_node("Identity", ["operands/key_map"], ["f/key_map"]),
         helper.make_node("Identity", ["operands/value_weight"], ["f/value_map"]),
         helper.make_node("Identity", ["operands/value_bias"], ["f/value_bias"])],
        "folded_operands", [],
        [out(n) for n in ("f/keys", "f/values", "f/key_map", "f/value_map", "f/value_bias")],
        [init("f/empty", np.zeros((0, 0, C), np.float32))])
    g.node.append(helper.make_node("If", ["key_value"], list(OPERAND_NAMES), name="operands",
                                   then_branch=cached, else_branch=folded))
    g.input.append(helper.make_tensor_value_info("key_value", TensorProto.BOOL, []))
    g.output.extend([out(n) for n in OPERAND_NAMES])
    return graph_model
