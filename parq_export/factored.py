"""The memory in factored form: what the exported graphs compute instead of the memory.

The cross-attention's memory, tokens s = (view, row, column) of the stride-4 map, is

    m_s = [P2_s | up(P3)_s | up(P4)_s | up(P5)_s] + W2 r_s + b2                  (C = 4 F)

with P_l (N, h_l, w_l, F) the FPN levels at their own resolution, ``up`` the bilinear resize to
P2's size (align_corners=False: a fixed matrix on each axis, ``resize_matrix``), and
r_s = ReLU(W1 x_s + b1) (C wide) the hidden layer of the ray MLP.  Everything that reads the
memory is linear in it, so it can read the factors instead:

* the query content, a bilinear sample of m averaged over views, is the same sample of the
  levels and of r, with W2 applied to the (K, C) result, plus b2 times the sum of the weights
  (the runtime samples; ``content`` does the rest);
* in the folded attention, head h scores a_h . m_s with a_h = q_h W_k,h: that is
  (a_h block 0) . P2_s + (a_h W2) . r_s + up((a_h block l) . P_l)_s, the coarse levels scored
  at their own resolution and the (K, h_l, w_l) score maps resized, plus a constant that
  softmax removes; the weighted sum is (sum_s w_s P2_s, up^T(w) . P_l, W2 sum_s w_s r_s + b2),
  with W_v,h applied after it (``FactoredWeights`` holds W_k,h W2 and W_v,h W2 folded).

What it saves: the ray MLP's second layer (2 S C^2 multiply-adds per snippet; 30 GFLOP of the
authors' 100 GFLOP backbone) and the resized copies of P3..P5, for per-iteration attention over
F + C + F (S_3 + S_4 + S_5) / S channels instead of C: 1.33 C for the authors' configuration.
The cached form projects keys and values from the same factors once per snippet.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .backbone import concat_levels


def resize_matrix(size_out: int, size_in: int) -> torch.Tensor:
    """(size_out, size_in): bilinear resize along one axis, align_corners=False, exactly as
    F.interpolate computes it (y = U x)."""
    eye = torch.eye(size_in, dtype=torch.float32)[None, None]
    return F.interpolate(eye, size=(size_out, size_in), mode="bilinear",
                         align_corners=False)[0, 0]


class FactoredWeights(nn.Module):
    """Per-head maps of the cross-attention onto the factors, from the layer's key/value
    weights W_k, W_v (C x C, head h = rows h d .. (h + 1) d) and the ray MLP's second layer
    W2 (C x C), b2:

    key_maps[l] (H, d, F) = W_k,h on channel block l; key_ray (H, d, C) = W_k,h W2;
    value_maps[l] (H, F, d) = (W_v,h on block l)^T; value_ray (H, C, d) = (W_v,h W2)^T;
    value_bias (H, 1, d) = b_v,h + W_v,h b2.  They depend on weights only: the export folds
    them into constants."""

    def __init__(self, attention: nn.MultiheadAttention, ray_out: nn.Linear, heads: int,
                 levels: int = 4):
        super().__init__()
        self.attention, self.ray_out, self.heads, self.levels = attention, ray_out, heads, levels

    def forward(self):
        W, b = self.attention.in_proj_weight, self.attention.in_proj_bias
        C = W.shape[1]
        H, d, Fc = self.heads, C // self.heads, C // self.levels
        W_k = W[C:2 * C].reshape(H, d, C)
        W_v = W[2 * C:].reshape(H, d, C)
        W2, b2 = self.ray_out.weight, self.ray_out.bias
        blocks = [slice(i * Fc, (i + 1) * Fc) for i in range(self.levels)]
        return {"key_maps": [W_k[..., s] for s in blocks], "key_ray": W_k @ W2,
                "value_maps": [W_v[..., s].transpose(1, 2) for s in blocks],
                "value_ray": (W_v @ W2).transpose(1, 2),
                "value_bias": b[2 * C:].reshape(H, 1, d) + (W_v @ b2).reshape(H, 1, d)}


def folded_attention(q: torch.Tensor, levels: list, ray_hidden: torch.Tensor, weights: dict,
                     resize: list) -> torch.Tensor:
    """Cross-attention of one snippet on the factors, per head, never forming the memory.

    q (H, K, d) queries already projected and scaled; levels P2..P5 (N, h_l, w_l, F);
    ray_hidden (N, h, w, C); weights from :class:`FactoredWeights`; resize[l - 1] = (rows
    (h, h_l), columns (w, w_l)) for the coarse levels.  Returns (H, K, d) (before the output
    projection)."""
    H, K, _ = q.shape
    N, h, w, Fc = levels[0].shape
    P2 = levels[0].reshape(-1, Fc)                                          # (S, F)
    R = ray_hidden.reshape(P2.shape[0], -1)                                 # (S, C)
    a = [(q @ m).reshape(H * K, -1) for m in weights["key_maps"]]          # (HK, F) each
    scores = a[0] @ P2.T + (q @ weights["key_ray"]).reshape(H * K, -1) @ R.T
    scores = scores.reshape(H * K, N, h, w)
    for level, a_l, (rows, cols) in zip(levels[1:], a[1:], resize):
        _, hl, wl, _ = level.shape
        coarse = (a_l @ level.reshape(-1, Fc).T).reshape(H * K, N, hl, wl)
        scores = scores + rows @ coarse @ cols.T
    attn = torch.softmax(scores.reshape(H * K, -1), -1)                     # (HK, S)
    ctx = ((attn @ P2).reshape(H, K, -1) @ weights["value_maps"][0]
           + (attn @ R).reshape(H, K, -1) @ weights["value_ray"])
    attn = attn.reshape(H * K, N, h, w)
    for level, value_map, (rows, cols) in zip(levels[1:], weights["value_maps"][1:], resize):
        _, hl, wl, _ = level.shape
        pooled = (rows.T @ attn @ cols).reshape(H * K, -1)                   # up^T(w)
        ctx = ctx + (pooled @ level.reshape(-1, Fc)).reshape(H, K, -1) @ value_map
    return ctx + weights["value_bias"]


def content(query_features: torch.Tensor, query_ray_hidden: torch.Tensor,
            query_weight: torch.Tensor, ray_out: nn.Linear) -> torch.Tensor:
    """Query content (K, C) from the sampled factors: features (K, C) + W2 ray_hidden (K, C)
    + b2 * weight (K, 1) (the sum of the bilinear weights over views, divided by the count)."""
    return query_features + F.linear(query_ray_hidden, ray_out.weight) \
        + query_weight * ray_out.bias


def memory(levels: list, ray_hidden: torch.Tensor, ray_out: nn.Linear) -> torch.Tensor:
    """The memory (N, h, w, C) from its factors (for the cached form's projections)."""
    f = concat_levels([p.permute(0, 3, 1, 2) for p in levels]).permute(0, 2, 3, 1)
    encoding = F.linear(ray_hidden.reshape(-1, ray_hidden.shape[-1]), ray_out.weight,
                        ray_out.bias)                                  # 2-D: one Gemm
    return f + encoding.reshape(f.shape)
